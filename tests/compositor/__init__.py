"""Tests of the compositor: composite fields, renderers and image output."""
