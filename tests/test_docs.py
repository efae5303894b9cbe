"""The README and docs/ stay short, correct and consistent with the code (fast: no FE).

- README.md is at most 12,000 bytes;
- every ```toml block of README.md and docs/*.md parses, and every block that is a
  configuration (a top-level key of skinfem.config) loads with ``load_config``;
- every relative markdown link of README.md and docs/*.md points to an existing file;
- every ``skinid <command>`` the README names (in code) is a command of the console script.
"""

from __future__ import annotations

import argparse
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_BYTES = 12_000

FENCE = re.compile(r"^(```+|~~~+)([^\n`]*)\n(.*?)^\1[ \t]*$", re.S | re.M)
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1", re.S)


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


def _blocks(text: str) -> list[tuple[str, str]]:
    """(info string, body) of every fenced code block."""
    return [(m.group(2).strip(), m.group(3)) for m in FENCE.finditer(text)]


def _prose(text: str) -> str:
    """The text without fenced code blocks and inline code (links in code are not links)."""
    text = FENCE.sub("", text)
    return INLINE_CODE.sub("", text)


def _toml_blocks():
    for page in PAGES:
        for k, (info, body) in enumerate(_blocks(page.read_text(encoding="utf-8"))):
            if info.split()[:1] == ["toml"]:
                yield pytest.param(page, body, id=f"{page.relative_to(ROOT)}#{k}")


def test_readme_size():
    size = README.stat().st_size
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes; move details into docs/ (limit {README_MAX_BYTES})"


def test_there_are_toml_examples():
    assert list(_toml_blocks()), "no ```toml block in README.md or docs/*.md"


@pytest.mark.parametrize("page, body", list(_toml_blocks()))
def test_toml_blocks_parse_and_load(page, body, tmp_path):
    from skinfem.config import SECTIONS, load_config

    try:
        data = tomllib.loads(body)
    except tomllib.TOMLDecodeError as exc:
        pytest.fail(f"{page.relative_to(ROOT)}: a ```toml block does not parse: {exc}\n{body}")
    if set(data) & ({"name"} | set(SECTIONS)):  # a configuration file: every key must be valid
        path = tmp_path / "example.toml"
        path.write_text(body, encoding="utf-8")
        load_config(path)  # raises ConfigError naming the bad key


@pytest.mark.parametrize("page", PAGES, ids=_ids(PAGES))
def test_relative_links_exist(page):
    missing = []
    for target in LINK.findall(_prose(page.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
            continue  # external (http:, mailto:, ...) or an anchor in the same page
        path = target.split("#", 1)[0].split("?", 1)[0]
        if not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)}: links to missing files: {missing}"


def _subcommands(parser: argparse.ArgumentParser) -> set[str]:
    actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return set(actions[0].choices) if actions else set()


def test_readme_commands_exist():
    import inference.__main__ as inference_cli
    import surrogate.__main__ as surrogate_cli
    from skinfem.cli import ROUTES

    # a command routed to a package must be known there too
    for name, (module, _) in ROUTES.items():
        if module == "inference.__main__":
            assert name in inference_cli.COMMANDS, name
    actions = {
        "surrogate": _subcommands(surrogate_cli.build_parser()),
        "study": _subcommands(inference_cli.build_parser("skinid study")),
    }
    text = README.read_text(encoding="utf-8")
    inline = [m.group(2) for m in INLINE_CODE.finditer(FENCE.sub("", text))]
    code = "\n".join([body for _, body in _blocks(text)] + inline)
    code = re.sub(r"(^|\s)#.*", "", code, flags=re.M)  # shell comments are prose
    named = re.findall(r"\bskinid[ \t]+([a-z][a-z0-9_-]*)(?:[ \t]+([a-z][a-z0-9_-]*))?", code)
    assert named, "the README names no skinid command"
    for command, action in named:
        assert command in ROUTES, f"README names 'skinid {command}', which is not a command ({', '.join(ROUTES)})"
        if command in actions and action and not action.startswith("-"):
            known = sorted(actions[command])
            assert action in actions[command], f"README names 'skinid {command} {action}'; known: {known}"
