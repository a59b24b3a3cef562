"""Sphinx roles in help text become what they name."""

from __future__ import annotations

from regnf.cli.help_text import plain_help


def test_a_constant_becomes_its_value_and_other_roles_their_names() -> None:
    text = ("at most :data:`MAX_VIEWS` views of :data:`regnf.compositor.render_folder.MAX_PIXELS` pixels; "
            "see :func:`~regnf.render.sphere_tracer.render_many`, :mod:`regnf.datasets.variation` and :attr:`shortlist`")
    from regnf.compositor.render_folder import MAX_PIXELS
    from regnf.datasets.generate_config import MAX_VIEWS

    assert plain_help(text, ["regnf.datasets.generate_config"]) == (
        f"at most {MAX_VIEWS:,} views of {MAX_PIXELS:,} pixels; see render_many, regnf.datasets.variation and shortlist")


def test_a_name_it_cannot_find_stays_a_name() -> None:
    assert plain_help(":data:`NO_SUCH_CONSTANT` and :data:`regnf.no_such_module.X`", ["regnf.cli.app"]) == \
        "NO_SUCH_CONSTANT and X"


def test_compact_help_keeps_the_own_options_and_sums_up_each_group() -> None:
    from regnf.cli.help_text import compact_help

    def box(title: str, *body: str) -> list[str]:
        """A box as tyro draws it, 60 characters wide."""
        return [f"╭─ {title} ".ljust(59, "─") + "╮", *(f"│ {x}".ljust(59) + "│" for x in body), "╰" + "─" * 58 + "╯"]

    lines = ["usage: regnf x [-h] [OPTIONS]", "", "Do x.", "",
             *box("options", "--a INT", "      The a. (default: 1)"),
             *box("g options", "What g holds.", "─" * 56, "--g.b, --g.no-b", "      The b.",
                  "--g.a-very-long-flag,", "--g.no-a-very-long-flag", "      A flag, wrapped."),
             *box("g.h options", "What g.h holds.", "─" * 56, "--g.h.c FLOAT", "      The c.")]
    short = compact_help("\n".join(lines), "x").splitlines()
    assert short[:8] == lines[:8]  # usage, description and the own options as they were
    assert short[8] == "╭─ g options (3, listed by --help-all) ".ljust(59, "─") + "╮"
    assert short[9:] == [lines[9], lines[-1], "Every setting of every group: regnf x --help-all"]
    # A command without groups keeps its help as it is.
    assert compact_help("\n".join(lines[:8]), "x") == "\n".join(lines[:8]) + "\n"
