"""--help of the commands: defaults shown where there is one, never "(default: None)"."""

from __future__ import annotations

from pathlib import Path

from homogenization.cli import plot
from warp_hcell.core.cli import command_parser


def test_defaults_shown_but_not_on_required_flags_or_none_defaults():
    parser = command_parser("homogenization.plotting", "test", device=False)
    parser.add_argument("--out", type=Path, required=True, help="figure file")
    parser.add_argument("--title", default=None, help="figure title (leave out: what the runs share)")
    parser.add_argument("--dpi", type=int, default=150, help="resolution")
    text = " ".join(parser.format_help().split())
    assert "(default: None)" not in text
    assert "--out OUT figure file --title TITLE figure title (leave out: what the runs share) --dpi" in text
    assert "resolution (default: 150)" in text


def test_plot_help_has_no_default_none():
    text = " ".join(plot.build_parser().format_help().split())
    assert "(default: None)" not in text
    assert "--out OUT figure file: .png, .pdf or .svg --deviator" in text
    assert "(default: q)" in text


def test_readme_names_every_command_and_writes_figures_under_runs():
    import re

    from homogenization.cli.hmodel import COMMANDS

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    listed = re.search(r"Every subcommand \(([^)]*)\)", readme)
    assert listed and re.findall(r"`(\w+)`", listed.group(1)) == list(COMMANDS)
    for page in (root / "README.md", *sorted((root / "docs").glob("*.md"))):
        for out in re.findall(r"^hmodel plot .*--out (\S+)", page.read_text(), flags=re.M):
            assert out.startswith("runs/"), f"{page.name}: hmodel plot writes {out} outside runs/"
