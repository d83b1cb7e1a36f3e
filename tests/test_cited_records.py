"""Every benchmark record the README and docs/ cite exists in benchmarks/results/ (records get renamed when a new
measurement takes a name; a citation left pointing at nothing is a figure a reader cannot check)."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
CITATION = re.compile(r"(?<![\w.-])([A-Za-z][\w*{},-]*\.(?:json|png))")


def expand_braces(name: str) -> list[str]:
    """``a_{1,0p1}_b.json`` → ``a_1_b.json``, ``a_0p1_b.json`` (one level, as the docs write them)."""
    m = re.search(r"\{([^{}]*)\}", name)
    if not m:
        return [name]
    return [x for part in m.group(1).split(",") for x in expand_braces(name[:m.start()] + part + name[m.end():])]


def cited_records(text: str, prefixes: set[str]) -> set[str]:
    """The names in ``text`` that read as results records: a .json/.png name whose first ``_``-separated word is
    the first word of an existing record (``fidelity``, ``fit``, ``demo``, …), globs and braces kept."""
    return {name for name in CITATION.findall(text) if re.split(r"[_.]", name, maxsplit=1)[0] in prefixes}


def test_expand_braces_and_citation_parsing():
    assert expand_braces("fit_{1,0p1}_half.json") == ["fit_1_half.json", "fit_0p1_half.json"]
    text = ("see `fidelity_wide.json`, benchmarks/results/demo.json and manifest.json, `…_seeds_iter1.json`, "
            "`fit_oracle_wide_depth_*.json`")
    assert cited_records(text, {"fidelity", "demo", "fit"}) == {"fidelity_wide.json", "demo.json",
                                                                "fit_oracle_wide_depth_*.json"}


def test_every_cited_record_exists():
    records = [p.name for p in RESULTS.iterdir() if p.suffix in (".json", ".png")]
    prefixes = {re.split(r"[_.]", name, maxsplit=1)[0] for name in records}
    missing = []
    for doc in DOCS:
        for name in sorted(cited_records(doc.read_text(), prefixes)):
            if not any(list(RESULTS.glob(pattern)) for pattern in expand_braces(name)):
                missing.append(f"{doc.relative_to(ROOT)}: {name}")
    assert not missing, "cited records missing from benchmarks/results/:\n" + "\n".join(missing)
