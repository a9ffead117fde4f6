"""CITATION.cff is a valid citation file (version 1.2.0's required keys), names the release the package is, and says
what README's "How to cite" says."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

import overhang_framework

ROOT = Path(__file__).resolve().parents[1]


def test_the_citation_file_names_this_release_and_the_paper_as_readme_does():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0"
    assert all(cff.get(k) for k in ("message", "title", "authors", "type"))
    assert all("name" in a or ("family-names" in a and "given-names" in a) for a in cff["authors"])
    assert cff["version"] == overhang_framework.__version__
    paper = cff["preferred-citation"]
    assert paper["type"] == "conference-paper" and all(paper.get(k) for k in ("title", "authors", "year"))
    readme = (ROOT / "README.md").read_text().split("## How to cite", 1)[1].split("\n## ", 1)[0]
    entries = dict(re.findall(r"@(\w+)\{(\w+),(.*?)\n\}", readme, re.S)[i][1:] for i in range(2))
    fields = {key: dict(re.findall(r"(\w+)\s*=\s*\{+(.*?)\}+,?\n", body + "\n")) for key, body in entries.items()}
    assert fields["shen2026overhang"]["title"] == paper["title"]
    assert fields["shen2026overhang"]["year"] == str(paper["year"])
    assert fields["shen2026overhang"]["author"] == " and ".join(
        f"{a['family-names']}, {a['given-names']}" for a in paper["authors"])
    assert fields["overhang_framework"]["version"] == cff["version"] and fields["overhang_framework"]["title"] == cff["title"]
