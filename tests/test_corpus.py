"""The hostile-input corpus (tests/corpus/): what the script writes, and every case against the service.

``bench/corpus.py`` writes the corpus, ``bench/hostile.py`` runs it (see their docstrings for the
checks: the documented error, no crash, no stored byte changed, other sessions' latency bound).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.corpus import DEFAULT_OUT, generate, manifest_text, write
from randt.cli.errors import ExitCode
from randt.wire.codes import ErrorCode

CORPUS = DEFAULT_OUT


def _files(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.suffix != ".py" and "__pycache__" not in p.parts
    }


def test_the_committed_corpus_is_what_the_script_writes(tmp_path: Path) -> None:
    n = write(tmp_path)
    assert n >= 60
    assert _files(tmp_path) == _files(CORPUS), "run `python -m bench.corpus` and commit tests/corpus/"


def test_the_corpus_covers_the_three_surfaces_with_documented_outcomes() -> None:
    manifest, files = generate()
    assert (CORPUS / "cases.json").read_text(encoding="utf-8") == manifest_text(manifest)
    by_surface: dict[str, int] = {}
    for case in manifest:
        by_surface[case["surface"]] = by_surface.get(case["surface"], 0) + 1
        assert case["description"]
        expect = case["expect"]
        if case["surface"] == "wire":
            assert expect["answer"] in ("error", "pose", "none", "pose_or_error")
            for code in expect.get("codes", []):
                ErrorCode(code)  # a documented code (docs/wire-format.md is tested against the enum)
        elif case["surface"] == "http":
            assert expect["status"] in (403, 404, 422) and expect["body"] in (
                "validation",
                "not_found",
                "detail",
            )
        else:
            ExitCode(expect["exit"])
    assert by_surface["wire"] >= 60 and by_surface["http"] >= 40 and by_surface["file"] >= 15, by_surface
    # big payloads are recipes, not committed files
    assert max(len(b) for b in files.values()) <= 64 * 1024
    recipes = [c for c in manifest if c["surface"] == "wire" and "file" not in c["payload"]]
    assert any(c["payload"]["recipe"]["kind"] == "map_bomb" for c in recipes)


def test_every_http_route_has_traversal_cases() -> None:
    """Each path and query parameter of service/api/*.py gets '..', an encoded '..' or a NUL."""
    targets = [
        c["target"]
        for c in json.loads((CORPUS / "cases.json").read_text())["cases"]
        if c["surface"] == "http"
    ]
    for prefix in (
        "/maps/..",
        "/maps/%2e%2e/tiles",
        "/maps/..%2F",
        "/maps/a%00b/metadata.yaml",
        "/maps/..%2F",
        "/maps/%2e%2e/export",
        "/sessions/../",
        "/sessions/{vehicle}/%2e%2e",
        "/sessions/{vehicle}/a%00b/trajectory",
        "/maps/{map}/tiles/..",
        "/maps/{map}/tiles/0/%2e%2e",
        "/maps/{map}/tiles/0/0?format=..",
        "/maps/{map}/export?format=..",
        "/maps/{map}/export?bbox=..",
        "/maps/{map}/tiles?bbox=%2e%2e",
        "/sessions/{vehicle}/{session}/trajectory?format=..",
        "/sessions?state=..",
        "/static/..",
    ):
        assert any(t.startswith(prefix) for t in targets), prefix


@pytest.fixture(scope="module")
def corpus_report():
    from bench.hostile import run_corpus

    return run_corpus(CORPUS)


_NAMES = [c["name"] for c in json.loads((CORPUS / "cases.json").read_text(encoding="utf-8"))["cases"]]


@pytest.mark.slow
@pytest.mark.parametrize("name", _NAMES)
def test_case(corpus_report, name: str) -> None:
    result = next(r for r in corpus_report.results if r.name == name)
    assert result.passed, f"{result.checks}: {result.detail}"
