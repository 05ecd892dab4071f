"""``recon filter IN OUT``: its options come from the stage's declaration (``recon_cli.stages.filter.SPEC``)."""

from __future__ import annotations

from recon_cli.cli.options import stage_command

cmd = stage_command("filter")
