"""Sphinx roles in help text become what they name."""

from __future__ import annotations

from regnf.help_text import plain_help


def test_a_constant_becomes_its_value_and_other_roles_their_names() -> None:
    text = ("at most :data:`MAX_VIEWS` views of :data:`regnf.compositor.render_folder.MAX_PIXELS` pixels; "
            "see :func:`~regnf.neural_fields.sphere_tracer.render_many`, :mod:`regnf.variation` and :attr:`shortlist`")
    from regnf.compositor.render_folder import MAX_PIXELS
    from regnf.generate_config import MAX_VIEWS

    assert plain_help(text, ["regnf.generate_config"]) == (
        f"at most {MAX_VIEWS:,} views of {MAX_PIXELS:,} pixels; see render_many, regnf.variation and shortlist")


def test_a_name_it_cannot_find_stays_a_name() -> None:
    assert plain_help(":data:`NO_SUCH_CONSTANT` and :data:`regnf.no_such_module.X`", ["regnf.cli"]) == \
        "NO_SUCH_CONSTANT and X"
