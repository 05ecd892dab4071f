"""``python -m recon_cli.tools.readme README.md``: rewrite the README's parameter tables.

A table sits between ``<!-- params: STAGE -->`` and ``<!-- /params -->`` and is
:meth:`recon_cli.params.StageSpec.markdown_table` of the stage's declaration; a test fails
when the README and the declarations disagree.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Sequence

from recon_cli.stages import get_spec

_BLOCK = re.compile(r"(<!-- params: ([a-z0-9_-]+) -->\n)(.*?)(<!-- /params -->)", re.DOTALL)


def readme_tables(text: str) -> dict[str, str]:
    """The parameter tables in README ``text``: stage name -> table text (between the markers)."""
    return {m.group(2): m.group(3).strip() for m in _BLOCK.finditer(text)}


def render_readme(text: str) -> str:
    """README ``text`` with every marked parameter table regenerated from the declarations."""

    def sub(m: re.Match) -> str:
        return m.group(1) + get_spec(m.group(2)).markdown_table() + "\n" + m.group(4)

    return _BLOCK.sub(sub, text)


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite the tables of the README named in ``argv`` (default ``README.md``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    path = args[0] if args else "README.md"
    with open(path, encoding="utf-8") as f:
        old = f.read()
    new = render_readme(old)
    if new != old:
        with open(path, "w", encoding="utf-8") as f:
            f.write(new)
        print(f"{path}: parameter tables updated")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
