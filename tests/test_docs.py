"""The documentation is tested like the code.

* Every ```python block of README.md and of docs/**/*.md runs: a page's blocks run in
  order in one namespace, in a fresh subprocess (float64, the test run's compilation
  cache), with the repository's ``jtraj`` on the path and a temporary working
  directory. A block is skipped only where the comment right above it says why
  (``<!-- skip-test: REASON -->``: an optional extra, the network, or a feature not
  built yet); a page whose examples take minutes says ``<!-- docs-test: slow -->`` and
  runs with ``-m slow``.
* The README stays short, and its test command is the one ``.ci/run`` runs.
* No tracked file outside ``CHANGELOG.md`` and the benchmarks page (the one place for a
  figure's date and machine) holds a development date or work-log talk.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import subprocess
import sys
import textwrap

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^```(\w*)\s*$")
_SKIP = re.compile(r"^<!--\s*skip-test:\s*(\S.*?)\s*-->\s*$")
_SLOW = re.compile(r"<!--\s*docs-test:\s*slow\b")


def code_blocks(text: str) -> list[dict]:
    """The ```python blocks of a Markdown text, in order: ``{"code", "line", "skip"}``
    (``line``: 1-based line of the fence; ``skip``: the reason of a ``skip-test`` comment
    on the last non-blank line before the fence, else None). An unclosed fence raises."""
    lines = text.splitlines()
    out, i, previous = [], 0, ""
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if m is None:
            if lines[i].strip():
                previous = lines[i].strip()
            i += 1
            continue
        start, lang = i, m.group(1)
        i += 1
        body = []
        while i < len(lines) and not lines[i].startswith("```"):
            body.append(lines[i])
            i += 1
        if i == len(lines):
            raise ValueError(f"unclosed code fence at line {start + 1}")
        if lang == "python":
            skip = _SKIP.match(previous)
            out.append({"code": "\n".join(body) + "\n", "line": start + 1, "skip": skip.group(1) if skip else None})
        previous = lines[i].strip()
        i += 1
    return out


def _pages() -> list[pathlib.Path]:
    return [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))


def _page_params():
    params = []
    for page in _pages():
        text = page.read_text(encoding="utf-8")
        if not any(b["skip"] is None for b in code_blocks(text)):
            continue
        rel = page.relative_to(ROOT).as_posix()
        marks = [pytest.mark.slow] if _SLOW.search(text) else []
        params.append(pytest.param(rel, id=rel, marks=marks))
    return params


# Runs in the subprocess: the blocks of one page, in order, in one namespace.
_RUNNER = textwrap.dedent("""
    import json, os, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    cache = os.environ.get("JTRAJ_TEST_CACHE")
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    import time
    blocks = json.load(open(sys.argv[1]))
    namespace = {"__name__": "__main__"}
    for b in blocks:
        print(f"--- {b['where']}", flush=True)
        t0 = time.perf_counter()
        exec(compile(b["code"], b["where"], "exec"), namespace)
        print(f"=== {time.perf_counter() - t0:.1f} s", flush=True)
""")


@pytest.mark.parametrize("page", _page_params())
def test_code_blocks_run(page, tmp_path):
    blocks = code_blocks((ROOT / page).read_text(encoding="utf-8"))
    runnable = [{"code": b["code"], "where": f"{page}:{b['line']}"} for b in blocks if b["skip"] is None]
    spec = tmp_path / "blocks.json"
    spec.write_text(json.dumps(runnable))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
               MPLBACKEND="Agg")
    work = tmp_path / "work"
    work.mkdir()
    proc = subprocess.run([sys.executable, "-c", _RUNNER, str(spec)], cwd=work, env=env, capture_output=True,
                          text=True, timeout=1800)
    print(proc.stdout)  # each block's wall time, shown by pytest -s or on failure
    assert proc.returncode == 0, f"a code block of {page} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-8000:]}"
    # every runnable block was reached, in order
    assert [ln[4:] for ln in proc.stdout.splitlines() if ln.startswith("--- ")] == [b["where"] for b in runnable]


def test_code_blocks_parser():
    text = textwrap.dedent("""\
        # Title

        ```python
        x = 1
        ```

        <!-- skip-test: needs the optional robots extra -->
        ```python
        import missing_extra
        ```

        ```bash
        echo not python
        ```

        Some text between.
        ```python
        y = x + 1

        assert y == 2
        ```
        """)
    blocks = code_blocks(text)
    assert [b["line"] for b in blocks] == [3, 8, 17]
    assert [b["skip"] for b in blocks] == [None, "needs the optional robots extra", None]
    assert blocks[0]["code"] == "x = 1\n"
    assert blocks[2]["code"] == "y = x + 1\n\nassert y == 2\n"
    with pytest.raises(ValueError, match="unclosed"):
        code_blocks("```python\nx = 1\n")


def test_skips_are_explained_and_rare():
    """Every skipped block names its reason, and at most a few blocks are skipped."""
    skipped = []
    for page in _pages():
        for b in code_blocks(page.read_text(encoding="utf-8")):
            if b["skip"] is not None:
                assert len(b["skip"]) >= 10, f"{page}:{b['line']}: say why the block is skipped"
                skipped.append(f"{page.name}:{b['line']}")
    assert len(skipped) <= 4, skipped


def test_readme_is_short_and_its_test_command_is_cis():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 250
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert ".venv/bin/python -m pip install --quiet -e '.[test]'" in ci
    assert "\n.venv/bin/python -m pytest\n" in ci
    assert "```bash\n.venv/bin/python -m pytest\n```" in readme
    assert ".venv/bin/pip install -e '.[test]'" in readme


def _tracked_files() -> list[pathlib.Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / p for p in out.decode().split("\0") if p]


#: where a date may stand: the changelog, and beside each benchmark table
_DATES_ALLOWED = {"CHANGELOG.md", "docs/benchmarks.md"}
_DATE = re.compile(r"\b20\d\d-[01]\d\b")
_WORKLOG = re.compile(r"\bses" r"sions?\b|\b(?:twenty|thirty|forty|fifty)-\w+ ses" r"sion", re.IGNORECASE)


def test_no_journal_in_tracked_files():
    found = []
    for path in _tracked_files():
        rel = path.relative_to(ROOT).as_posix()
        if rel == "CHANGELOG.md" or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data:  # binary (figures)
            continue
        for n, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
            if (_DATE.search(line) and rel not in _DATES_ALLOWED) or _WORKLOG.search(line):
                found.append(f"{rel}:{n}: {line.strip()[:100]}")
    assert not found, "development dates or work-log talk:\n" + "\n".join(found[:40])


def test_journal_patterns_catch_what_they_should():
    year, work = "20" + "26", "ses" + "sion"  # split, so that this file passes its own test
    assert _DATE.search(f"measured on {year}-12-04") and not _DATE.search(f"version 1.{year}")
    assert _WORKLOG.search(f"the thirty-first {work}") and _WORKLOG.search(f"two {work}s later")
    assert not _WORKLOG.search("a Ray cluster address")
