"""Every warning kind a stage records is explained in ``docs/warnings.md``.

The kinds are read from the source (the ``warn("kind", ...)`` calls, the fitter's
``step_failed("kind", ...)`` and the ``("warning", "kind", ...)`` notices of a fit, whose
outlier kind is chosen as ``"warning" if kind == "..."``), so a new
warning without its line in the docs fails here; the docs' table is read back as the set of
kinds it explains, so a kind left in the docs after its code went fails too.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PATTERN = re.compile(
    r"""(?:\.warn\(|step_failed\(|\(\s*"warning",|"warning" if kind == )\s*"(?P<kind>[a-z][a-z0-9-]+)\"""",
)


def kinds_in_source() -> set[str]:
    out = set()
    for package in ("stages", "streamer"):
        for path in (ROOT / package).rglob("*.py"):
            out |= {m["kind"] for m in PATTERN.finditer(path.read_text())}
    return out


def kinds_in_docs() -> set[str]:
    text = (ROOT / "docs" / "warnings.md").read_text()
    return set(re.findall(r"^\| `([a-z][a-z0-9-]+)` \|", text, re.M))


def test_the_source_records_the_warnings_this_test_knows_of():
    # the reading of the source finds the known kinds (a change of the calls' shape would
    # otherwise leave the test below comparing two empty sets)
    assert {"not-converged", "no-fit", "model-parts-missing", "window-refit-failed"} <= kinds_in_source()


def test_every_recorded_warning_is_explained_in_the_docs():
    source, docs = kinds_in_source(), kinds_in_docs()
    assert not source - docs, f"recorded but not explained in docs/warnings.md: {sorted(source - docs)}"
    assert not docs - source, f"explained in docs/warnings.md but recorded nowhere: {sorted(docs - source)}"
