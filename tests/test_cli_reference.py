"""recon_cli.cli.reference: the command-line reference page is each command's own ``--help``."""

from __future__ import annotations

from click.testing import CliRunner
from docutils.core import publish_doctree
from docutils.nodes import literal_block, section

from recon_cli.cli.main import cli
from recon_cli.cli.reference import WIDTH, command_names, reference_page, write_reference
from recon_cli.stages import stage_names

QUIET = {"report_level": 5, "halt_level": 5}


def _blocks() -> dict[str, str]:
    """The page's sections as a reader sees them: title -> the literal block under it."""
    tree = publish_doctree(reference_page(), settings_overrides=QUIET)
    out = {}
    for sec in tree.findall(section):
        blocks = [b for b in sec.children if isinstance(b, literal_block)]
        if blocks:
            out[sec[0].astext()] = blocks[0].astext()
    return out


def test_every_command_has_its_help_on_the_page():
    """Each command's section is its ``--help`` at the page's width, every stage included."""
    blocks = _blocks()
    names = command_names()
    assert set(stage_names()) <= set(names)
    assert {"run", "batch", "diff", "info", "convert", "warmup"} <= set(names)
    assert list(blocks) == ["recon", *(f"recon {n}" for n in names)]
    runner = CliRunner()
    for name in names:
        # the page's text is what `recon NAME --help` prints at the page's width
        got = runner.invoke(cli, [name, "--help"], prog_name="recon", terminal_width=WIDTH)
        assert got.exit_code == 0, name
        assert blocks[f"recon {name}"] == got.output.rstrip("\n"), name
    for name in stage_names():
        text = blocks[f"recon {name}"]
        assert text.startswith(f"Usage: recon {name} [OPTIONS] IN OUT")


def test_reference_is_written_once(tmp_path):
    """``write_reference`` writes index.rst, then nothing when called again with nothing changed."""
    out = str(tmp_path / "cli")
    assert write_reference(out) == [str(tmp_path / "cli" / "index.rst")]
    assert write_reference(out) == []  # unchanged: the file keeps its time
