"""The README is a quick start and the docs name nothing that does not exist (issue 35).

Fast: no training, no store. Checks README.md and docs/*.md for
- the README's length (a quick start: at most 150 lines) and its two commands (the test command is
  the last line of .ci/run, which CI runs);
- every ``physmend COMMAND --option`` written in code (inline or a fenced block) is a command and an
  option of the command line;
- every configuration key written ``group.key=…`` anywhere, or ``group.key`` in code, exists in the
  composed default configuration (the few keys whose children are free-form are listed below);
- every relative link to a file points at one that exists;
- docs/configuration.md is what docs/make_config_reference.py generates from conf/ today.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import io
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
MAX_README_LINES = 150
MAIN_COMMAND = "python3 -m venv .venv && .venv/bin/pip install -q --no-compile . && .venv/bin/physmend discover"

#: config groups whose keys the docs may name (conf/config.yaml's defaults)
GROUPS = ("diagnose", "sweep", "mask", "sensitivity", "symbolic", "propose", "train", "ude", "simulate",
          "tracking", "decide", "export", "discover", "operators", "data", "model")
#: model/data configs belong to a project: only these keys are the same for every project
PROJECT_KEYS = ("model.builder", "model.options", "model.corrections")
#: keys whose children are free-form (not in the shipped defaults), with the reason
DYNAMIC = {
    "symbolic.options": "the regression back end's own options (symbolic.options.generations for pyoperon …)",
    "simulate.options": "the solver's own options (max_steps …)",
    "symbolic.choice": "a Pareto index per state name of the user's model",
    "model.options": "the keyword arguments of the user's model builder",
}
#: a dotted word ending like this is a file name (sweep.py, model.py), not a key
FILE_SUFFIXES = ("py", "yaml", "yml", "json", "md", "html", "csv", "parquet", "db", "tex", "txt", "png")

#: ``group.key``, not inside a dotted name (``physmend.ude.drive``), not a call (``diagnose.run(cfg)``)
_KEY = re.compile(r"(?<![\w./+-])\+*(?P<key>(?:" + "|".join(GROUPS) + r")(?:\.[A-Za-z_]\w*)+)(?![\w(])(?P<eq>=)?")
_COMMAND = re.compile(r"(?<![\w./-])physmend\s+(?P<cmd>[a-z][\w-]*)(?P<rest>[^\n`|;&#]*)")
_LINK = re.compile(r"\]\((?P<target>[^)\s#]*)(?:#(?P<anchor>[^)\s]*))?\)")


def _code(text: str) -> list[str]:
    """The code in a Markdown text: fenced blocks and inline spans."""
    blocks = re.findall(r"^```[^\n]*\n(.*?)^```", text, flags=re.M | re.S)
    prose = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.M | re.S)
    return blocks + re.findall(r"`([^`\n]+)`", prose)


def _keys(text: str) -> set[str]:
    """Configuration keys named in ``text``: ``group.key=`` anywhere, ``group.key`` in code."""
    found = {m["key"] for m in _KEY.finditer(text) if m["eq"]}
    for code in _code(text):
        found |= {m["key"] for m in _KEY.finditer(code)}
    return {k for k in found if k.rsplit(".", 1)[-1] not in FILE_SUFFIXES}


def _commands(text: str) -> list[tuple[str, list[str]]]:
    """``(command, [--options])`` of every ``physmend COMMAND …`` written in code."""
    out = []
    for code in _code(text):
        for m in _COMMAND.finditer(code):
            out.append((m["cmd"], tuple(re.findall(r"(?<!\S)(--[a-z][\w-]*)", m["rest"]))))
    return out


@functools.cache
def _help(command: str) -> str | None:
    """``physmend COMMAND --help`` as printed, or None when the command line does not know it."""
    from physmend.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    return out.getvalue() if stop.value.code == 0 else None


@functools.cache
def _configs() -> tuple:
    from physmend.config import compose

    return compose([]), compose(["operators=extended"])


def _exists(key: str) -> bool:
    from omegaconf import DictConfig

    if any(key == d or key.startswith(d + ".") for d in DYNAMIC):
        return True
    for cfg in _configs():
        node = cfg
        for part in key.split("."):
            if not isinstance(node, DictConfig) or part not in node:
                break
            node = node[part]
        else:
            return True
    return False


def _named(extract) -> dict[str, set]:  # noqa: ANN001
    return {str(p.relative_to(ROOT)): set(extract(p.read_text())) for p in PAGES}


def test_the_readme_is_a_quick_start() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; a quick start has at most {MAX_README_LINES}"


def test_the_readme_commands_are_the_ones_ci_and_users_run() -> None:
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    lines = README.read_text().splitlines()
    tests = [line for line in lines if "-m pytest" in line]
    assert tests == [ci], f"README's test command must be .ci/run's last line {ci!r}, but README has {tests}"
    assert MAIN_COMMAND in lines, f"README's main command {MAIN_COMMAND!r} is missing"


def test_every_command_named_exists() -> None:
    stale = {}
    for page, named in _named(_commands).items():
        for command, options in sorted(named, key=str):
            help_text = _help(command)
            if help_text is None:
                stale.setdefault(page, []).append(f"physmend {command}")
                continue
            stale.setdefault(page, []).extend(
                f"physmend {command} {o}" for o in options if not re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", help_text))
    stale = {k: v for k, v in stale.items() if v}
    assert not stale, f"commands or options that the command line does not have: {stale}"


def test_every_configuration_key_named_exists() -> None:
    stale = {}
    for page, keys in _named(_keys).items():
        checked = {k for k in keys if k.split(".")[0] not in ("data", "model")
                   or any(k == p or k.startswith(p + ".") for p in PROJECT_KEYS)}
        missing = sorted(k for k in checked if not _exists(k))
        if missing:
            stale[page] = missing
    assert not stale, f"configuration keys that the composed configuration does not have: {stale}"


def _resolves(dotted: str) -> bool:
    """``physmend.a.b[.name]`` is a module or package of src/ (and ``name`` defined in it), or a name
    the code writes as a string (an MLflow tag such as ``physmend.model.structure``)."""
    src = ROOT / "src"
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        base = src.joinpath(*parts[:n])
        module = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
        if module.is_file():
            rest = parts[n:]
            if not rest:
                return True
            name = re.escape(rest[0])  # defined, assigned, or a lazy export ("Model": "model")
            pattern = rf"^\s*(?:def|class)\s+{name}\b|^{name}\s*[:=]|^\s*[\"']{name}[\"']\s*:"
            if len(rest) == 1 and re.search(pattern, module.read_text(), flags=re.M):
                return True
            break
    return any(f'"{dotted}"' in p.read_text() for p in (src / "physmend").rglob("*.py"))


def test_every_module_named_exists() -> None:
    stale = {}
    for page in PAGES:
        named = {m for code in _code(page.read_text()) for m in re.findall(r"(?<![\w./-])physmend(?:\.[A-Za-z_]\w*)+", code)}
        missing = sorted(m for m in named if m.rsplit(".", 1)[-1] not in FILE_SUFFIXES and not _resolves(m))
        if missing:
            stale[str(page.relative_to(ROOT))] = missing
    assert not stale, f"modules or names of physmend that do not exist: {stale}"


def _anchors(page: Path) -> set[str]:
    """The anchors GitHub gives the headings of a Markdown page (lower case, punctuation dropped)."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}


def test_every_relative_link_points_at_a_file_and_heading() -> None:
    broken = {}
    for page in PAGES:
        for m in _LINK.finditer(page.read_text()):
            target, anchor = m["target"], m["anchor"]
            if "://" in target or target.startswith("mailto:"):
                continue
            path = (page.parent / target) if target else page
            if not path.exists() or (anchor and path.suffix == ".md" and anchor not in _anchors(path)):
                broken.setdefault(str(page.relative_to(ROOT)), []).append(f"{target}#{anchor}" if anchor else target)
    assert not broken, f"links to files or headings that do not exist: {broken}"


def test_the_configuration_reference_is_current() -> None:
    spec = importlib.util.spec_from_file_location("make_config_reference", ROOT / "docs" / "make_config_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert (ROOT / "docs" / "configuration.md").read_text() == module.render(), (
        "docs/configuration.md is not what conf/ says today: run python docs/make_config_reference.py")


@pytest.mark.parametrize("text, keys", [
    ("`sweep.n_trials=500 sweep.workers=2`", {"sweep.n_trials", "sweep.workers"}),
    ("set train.lr=0.1 in prose; `physmend.ude.drive`, `stages/sweep.py`, `model.py`, `diagnose.run(cfg)`", {"train.lr"}),
    ("`++model.corrections=FILE`, plain mask.tolerance without =", {"model.corrections"}),
])
def test_the_key_finder_finds_keys(text: str, keys: set[str]) -> None:
    assert _keys(text) == keys


def test_the_checks_catch_stale_names() -> None:
    assert not _exists("train.no_such_key") and not _exists("sweep.n_trials.x")
    assert _exists("sweep.n_trials") and _exists("operators.pow") and _exists("symbolic.options.generations")
    assert _help("no-such-command") is None and "--config-dir" in (_help("diagnose") or "")
    assert "accept-and-reject" in _anchors(ROOT / "docs" / "propose.md")
    assert "the-quick-starts-main-command-over-time" in _anchors(ROOT / "benchmarks" / "README.md")
    assert _commands("run `physmend runs --json` then\n```\nphysmend select RUN_ID\n```") == [
        ("select", ()), ("runs", ("--json",))]
