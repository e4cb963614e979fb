"""The built documentation site carries no markup meant for another tool.

Run after ``mkdocs build`` (CI does): ``python scripts/check_site.py SITE_DIR``.  Fails (exit 1) on
any Sphinx role (``:func:`x```), reST double-backquote literal left raw inside rendered text,
or autorefs link that did not resolve, naming the page and the text.
"""

from __future__ import annotations

import re
import sys
from html.parser import HTMLParser
from pathlib import Path

ROLE = re.compile(r":(func|class|mod|meth|data|attr|exc|obj|ref|doc):`")
UNRESOLVED = re.compile(r"\[[^\]\n]+\]\[[\w.]+\]")  # [text][greyid.path] printed as text: a reference not found


class Text(HTMLParser):
    """The page's visible text, outside code blocks (where a role may be quoted on purpose)."""

    def __init__(self):
        super().__init__()
        self.depth, self.parts = 0, []

    def handle_starttag(self, tag, attrs):
        if tag in ("pre", "script", "style"):
            self.depth += 1

    def handle_endtag(self, tag):
        if tag in ("pre", "script", "style") and self.depth:
            self.depth -= 1

    def handle_data(self, data):
        if not self.depth:
            self.parts.append(data)


def problems(site: Path) -> list[str]:
    found = []
    for page in sorted(site.rglob("*.html")):
        parser = Text()
        parser.feed(page.read_text(encoding="utf-8"))
        text = "".join(parser.parts)
        for pattern, what in ((ROLE, "a Sphinx role"), (UNRESOLVED, "an unresolved cross-reference")):
            for match in pattern.finditer(text):
                context = text[max(0, match.start() - 40):match.end() + 40].replace("\n", " ")
                found.append(f"{page.relative_to(site)}: {what}: ...{context}...")
    return found


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not Path(argv[0]).is_dir():
        print("usage: python scripts/check_site.py SITE_DIR", file=sys.stderr)
        return 2
    found = problems(Path(argv[0]))
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
