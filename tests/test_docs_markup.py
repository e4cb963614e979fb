"""The API reference renders: docstrings in the one convention mkdocstrings reads, no Sphinx roles."""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import check_site  # noqa: E402

ROLE = re.compile(r":(func|class|mod|meth|data|attr|exc|obj):`")


def test_no_docstring_uses_a_sphinx_role():
    found = [f"{path.relative_to(ROOT)}:{number}" for path in sorted((ROOT / "src" / "greyid").rglob("*.py"))
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if ROLE.search(line)]
    assert not found, found


def test_the_site_check_finds_a_raw_role_and_an_unresolved_reference(tmp_path):
    (tmp_path / "good.html").write_text("<p>See <a href='x'>fit()</a>.</p><pre>:func:`quoted` in code</pre>")
    assert check_site.problems(tmp_path) == []
    (tmp_path / "bad.html").write_text("<p>See :func:`~.information.fisher_information` and "
                                       "[<code>fit()</code>][greyid.api.Model.fit].</p>")
    found = check_site.problems(tmp_path)
    assert any("a Sphinx role" in line for line in found) and any("unresolved" in line for line in found)
    assert check_site.main([str(tmp_path)]) == 1
