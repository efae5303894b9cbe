"""The README and docs/ stay short, correct and consistent with the code (fast: no FE).

- README.md is at most 12,000 bytes;
- every fenced block of README.md and docs/*.md says its language (``bash``, ``toml``,
  ``python`` or ``text``) and every block that is not ``text`` runs here:

  - ``bash``: each command (backslash continuations joined, comments dropped, ``mpirun -n N``,
    ``VAR=value`` and ``.venv/bin/`` prefixes removed) is checked without running it:
    ``skinid <command> ...`` (and ``python -m skinfem|surrogate|inference ...``) is parsed by
    that command's own argparse parser, which must accept it without error or deprecation
    warning, and its ``--config`` must load; ``python <script>.py ...`` names an existing file
    whose parser (built from the script's source, its heavy imports not run) accepts the
    arguments; ``make <target>`` is a target of the Makefile; other programs (pip, git, ...)
    must be listed in ``OTHER_PROGRAMS``. Usage lines are read as synopses: ``[optional]``
    parts, ``a | b`` and ``a|b`` alternatives (each tried: with every option, without the
    optional parts, and every alternative once), ``x ...`` repeats, a bare ``...`` elides
    arguments (required options are then not demanded) and placeholders (``FILE``, ``<x>``)
    stand for any value;
  - ``toml``: parses, and every block that is a configuration (a top-level key of
    skinfem.config) loads with ``load_config``;
  - ``python``: is executed (the effect registry replaced by a copy); the worked example of
    docs/criticism-overview.md also does what it says;

- the option examples in the commands' help (``--frames=-3,-2,-1``) parse;
- every relative markdown link of README.md and docs/*.md points to an existing file;
- every ``skinid <command>`` the README names (in code) is a command of the console script.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import importlib
import importlib.util
import io
import math
import re
import shlex
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

LANGUAGES = {"bash", "toml", "python", "text"}  # text: diagrams, file layouts, output (not run)
#: programs a ```bash block may name that need no check (installers, version control, shell)
OTHER_PROGRAMS = {
    "pip",
    "pip3",
    "git",
    "cd",
    "source",
    "export",
    "conda",
    "mamba",
    "apt",
    "apt-get",
    "sudo",
    "bash",
    "sh",
    "ls",
    "cat",
    "cp",
    "mv",
    "rm",
    "mkdir",
    "paraview",
    "sbatch",
    "srun",
    "jupyter",
}
PACKAGE_MODULES = {"skinfem", "surrogate", "inference"}  # python -m <package> is a skinid command line
PLACEHOLDER = re.compile(r"^(<[^<>]+>|[A-Z][A-Z0-9_]*)$")  # FILE, MU, N, <dir>: stands for any value
ENV_ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
PYTHON = re.compile(r"^python(3(\.\d+)?)?$")
HELP_EXAMPLE = re.compile(r"(--[a-z][a-z0-9-]*=[^\s()]+)")


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


def _blocks(text: str) -> list[tuple[str, str]]:
    """(info string, body) of every fenced code block."""
    return [(m.group(2).strip(), m.group(3)) for m in FENCE.finditer(text)]


def _prose(text: str) -> str:
    """The text without fenced code blocks and inline code (links in code are not links)."""
    text = FENCE.sub("", text)
    return INLINE_CODE.sub("", text)


def _all_blocks() -> list[tuple[Path, int, str, str]]:
    """(page, line of the opening fence, language, body) of every fenced block of the pages."""
    found = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for m in FENCE.finditer(text):
            found.append((page, text.count("\n", 0, m.start()) + 1, m.group(2).strip().split(" ")[0], m.group(3)))
    return found


BLOCKS = _all_blocks()


def _where(page: Path, line: int) -> str:
    return f"{page.relative_to(ROOT)}:{line}"


def _params(language: str):
    return [
        pytest.param(page, line, body, id=_where(page, line)) for page, line, lang, body in BLOCKS if lang == language
    ]


def _toml_blocks():
    for page, line, lang, body in BLOCKS:
        if lang == "toml":
            yield pytest.param(page, body, id=_where(page, line))


def test_readme_size():
    size = README.stat().st_size
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes; move details into docs/ (limit {README_MAX_BYTES})"


def test_every_block_names_a_known_language():
    assert BLOCKS, "no fenced block in README.md or docs/*.md"
    untagged = [_where(page, line) for page, line, lang, _ in BLOCKS if not lang]
    assert not untagged, f"fenced blocks without a language (use one of {sorted(LANGUAGES)}): {untagged}"
    unknown = [f"{_where(page, line)} ({lang})" for page, line, lang, _ in BLOCKS if lang and lang not in LANGUAGES]
    assert not unknown, f"fenced blocks in a language the tests do not run (use one of {sorted(LANGUAGES)}): {unknown}"


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


# ---- ```bash blocks: every command is checked without running it --------------------------------


def _shell_commands(body: str) -> list[list[str]]:
    """The commands of a shell block as word lists: continuation lines joined, comments dropped,
    ``a && b`` and ``a; b`` split."""
    commands = []
    for line in body.replace("\\\n", " ").splitlines():
        command: list[str] = []
        for word in shlex.split(line, comments=True):
            if word in ("&&", "||", ";"):
                commands.append(command)
                command = []
            else:
                command.append(word)
        commands.append(command)
    return [c for c in commands if c]


def _program(words: list[str]) -> tuple[str, list[str]]:
    """(program, arguments) of a command without its ``VAR=value``, ``mpirun -n N`` and
    ``.venv/bin/`` prefixes."""
    words = list(words)
    while words and ENV_ASSIGNMENT.match(words[0]):
        words.pop(0)
    if words and words[0] in ("mpirun", "mpiexec"):
        words.pop(0)
        while words and words[0].startswith("-"):
            del words[: 2 if words[0] in ("-n", "-np", "--np", "-c") else 1]
        while words and ENV_ASSIGNMENT.match(words[0]):
            words.pop(0)
    assert words, "an empty command"
    program = Path(words[0]).name if Path(words[0]).parent.name == "bin" else words[0]
    return program, words[1:]


class _Choice:
    """A choice of a synopsis: ``[a | b]`` (optional) or the word ``a|b``; alternatives are word sequences."""

    def __init__(self, alternatives: list[list], optional: bool):
        self.alternatives, self.optional = alternatives, optional


def _synopsis(words: list[str]) -> tuple[list, bool]:
    """(sequence of words and :class:`_Choice`, whether a bare ``...`` elides arguments) of a usage line."""
    symbols = []
    for word in words:
        core = word.lstrip("[")
        lead = len(word) - len(core)
        word, core = core, core.rstrip("]")
        symbols += ["["] * lead + ([core] if core else []) + ["]"] * (len(word) - len(core))
    elided = False

    def sequence(i: int, depth: int) -> tuple[list[list], int]:
        nonlocal elided
        alternatives: list[list] = [[]]
        while i < len(symbols):
            s = symbols[i]
            i += 1
            if s == "[":
                inner, i = sequence(i, depth + 1)
                alternatives[-1].append(_Choice(inner, optional=True))
            elif s == "]":
                assert depth, f"unbalanced ']' in: {' '.join(words)}"
                return alternatives, i
            elif s == "|":
                if not depth:
                    break  # a pipe: the rest is another program
                alternatives.append([])
            elif s == "...":
                elided |= not depth  # inside [...] it repeats the word before
            elif "|" in s:
                alternatives[-1].append(_Choice([[w] for w in s.split("|")], optional=False))
            else:
                alternatives[-1].append(s)
        assert not depth, f"unbalanced '[' in: {' '.join(words)}"
        return alternatives, i

    (top,), _ = sequence(0, 0)
    return top, elided


def _expansions(words: list[str]) -> tuple[list[list[str]], bool]:
    """(argument lists a usage line stands for, elided): with every optional part (first
    alternatives), without any, and each alternative of each choice once; placeholders -> 1."""
    tree, elided = _synopsis(words)
    choices = []

    def collect(seq, reach):  # reach: the selection of the enclosing alternatives
        for node in seq:
            if isinstance(node, _Choice):
                choices.append((node, reach))
                for k, alternative in enumerate(node.alternatives):
                    collect(alternative, {**reach, id(node): k})

    def expand(seq, selection):
        out = []
        for node in seq:
            if isinstance(node, str):
                out.append("1" if PLACEHOLDER.match(node) else node)
            elif (k := selection.get(id(node), 0)) >= 0:
                out += expand(node.alternatives[k], selection)
        return out

    collect(tree, {})
    selections = [{}, {id(c): -1 for c, _ in choices if c.optional}]
    selections += [
        {**reach, id(c): k} for c, reach in choices for k in range(-1 if c.optional else 1, len(c.alternatives)) if k
    ]
    variants = []
    for selection in selections:
        if (argv := expand(tree, selection)) not in variants:
            variants.append(argv)
    return variants, elided


def _relax(parser: argparse.ArgumentParser) -> None:
    """No option of ``parser`` or its sub-parsers is required any more (for an elided ``...``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _relax(sub)
        elif action.option_strings:
            action.required = False
    for group in parser._mutually_exclusive_groups:
        group.required = False


def _no_abbreviations(parser: argparse.ArgumentParser) -> None:
    """``parser`` and its sub-parsers take options spelled in full only (docs do not abbreviate)."""
    for _, sub in _walk(parser):
        sub.allow_abbrev = False


def _parse(parser: argparse.ArgumentParser, argv: list[str], relaxed: bool) -> str | None:
    """None if ``parser`` accepts ``argv`` (options spelled in full) quietly; otherwise what it says."""
    _no_abbreviations(parser)
    if relaxed:
        _relax(parser)
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            parser.parse_args(argv)
    except SystemExit as exc:
        return (err.getvalue().strip().splitlines() or [f"exit status {exc.code}"])[-1]
    return err.getvalue().strip() or None  # e.g. a deprecated spelling


def _command_parser(command: str) -> tuple[argparse.ArgumentParser, int]:
    """A fresh parser of ``skinid <command>`` and how many leading words of ``<command> ...`` it does not take."""
    from skinfem.cli import ROUTES

    module = importlib.import_module(ROUTES[command][0])
    if ROUTES[command][0] == "inference.__main__":  # one parser per command
        return module.build_parser(f"skinid {command}"), 1
    parser = module.build_parser()
    return parser, 0 if command in _subcommands(parser) else 1


def _check_config(argv: list[str]) -> str | None:
    """A ``--config`` preset, or file of this repository, that does not load: what is wrong."""
    from skinfem.config import ConfigError, load_config

    for k, word in enumerate(argv):
        value = argv[k + 1] if word == "--config" and k + 1 < len(argv) else word.partition("=")[2]
        if not (word == "--config" or word.startswith("--config=")) or not value or value == "1":
            continue
        if Path(value).suffix and not (ROOT / Path(value).parts[0]).exists():
            continue  # the reader's own file
        try:
            load_config(ROOT / value if Path(value).suffix else value)
        except ConfigError as exc:
            return str(exc)
    return None


def _check_skinid(argv: list[str]) -> list[str]:
    from skinfem.cli import ROUTES

    if argv in (["--version"], ["--help"], ["-h"]):
        return []
    if not argv or argv[0] not in ROUTES:
        return [f"'skinid {' '.join(argv[:1])}' is not a command ({', '.join(ROUTES)})"]
    problems = []
    variants, elided = _expansions(argv)
    for variant in variants:
        parser, skip = _command_parser(argv[0])
        if said := _parse(parser, variant[skip:], relaxed=elided):
            problems.append(f"skinid {' '.join(variant)}: {said}")
        elif said := _check_config(variant):
            problems.append(f"skinid {' '.join(variant)}: {said}")
    return problems


def _script_parser(path: Path) -> argparse.ArgumentParser | None:
    """The argparse parser of a script, built from its source alone: its module-level assignments
    that can run without imports, then the statements of its functions that make the parser (so
    no heavy import or computation runs). None if it builds none."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    namespace = {
        "argparse": argparse,
        "Path": Path,
        "__doc__": ast.get_docstring(tree, clean=False),
        "__file__": str(path),
        "__name__": "script_under_test",
    }
    for node in tree.body:
        if isinstance(node, ast.Assign | ast.AnnAssign):
            with contextlib.suppress(Exception):
                exec(compile(ast.Module([node], []), str(path), "exec"), namespace)
    makers = {
        "ArgumentParser",
        "add_argument",
        "add_mutually_exclusive_group",
        "add_argument_group",
        "add_subparsers",
        "add_parser",
        "set_defaults",
    }
    for function in (n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)):
        for node in function.body:
            calls = [c.func for c in ast.walk(node) if isinstance(c, ast.Call)]
            names = {f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "") for f in calls}
            if names & makers and not names & {"parse_args", "parse_known_args"}:
                try:
                    exec(compile(ast.Module([node], []), str(path), "exec"), namespace)
                except Exception:  # needs a name the script imports or computes: no parser from source
                    return None
        parsers = [v for v in namespace.values() if isinstance(v, argparse.ArgumentParser)]
        if parsers:
            parsers[0].prog = f"python {path.relative_to(ROOT)}"
            return parsers[0]
    return None


def _check_script(script: str, argv: list[str]) -> list[str]:
    path = ROOT / script
    if not path.is_file():
        return [f"python {script}: no such file"]
    problems = []
    parser_missing = _script_parser(path) is None
    variants, elided = _expansions(argv)
    for variant in variants:
        if parser_missing:  # no parser to ask: at least its options are in its source
            source = path.read_text(encoding="utf-8")
            unknown = [w.split("=")[0] for w in variant if w.startswith("--") and w.split("=")[0] not in source]
            problems += [f"python {script}: {w} does not appear in {script}" for w in unknown]
        elif said := _parse(_script_parser(path), variant, relaxed=elided):
            problems.append(f"python {script} {' '.join(variant)}: {said}")
    return problems


def _make_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    return {t for line in re.findall(r"^([^\s:=#][^:=#]*?)\s*::?(?!=)", text, re.M) for t in line.split()}


def _check_command(words: list[str]) -> list[str]:
    """What is wrong with one shell command of the docs (empty list if nothing)."""
    program, args = _program(words)
    if program == "skinid":
        return _check_skinid(args)
    if PYTHON.match(program):
        if args[:1] == ["-m"] and len(args) > 1:
            module, rest = args[1], args[2:]
            if module == "skinfem":
                return _check_skinid(rest)
            if module == "surrogate":  # python -m surrogate [surrogate] fit ...
                return _check_skinid(rest if rest[:1] == ["surrogate"] else ["surrogate", *rest])
            if module == "inference":
                from inference.__main__ import COMMANDS

                return _check_skinid(rest if rest[:1] and rest[0] in COMMANDS else ["infer", *rest])
            found = importlib.util.find_spec(module) is not None
            return [] if found else [f"python -m {module}: no such module"]
        if args[:1] and args[0].endswith(".py"):
            return _check_script(args[0], args[1:])
        return [f"{' '.join(words)}: a python command the docs test cannot check"]
    if program == "make":
        missing = [t for t in args if not t.startswith("-") and "=" not in t and t not in _make_targets()]
        return [f"make {t}: no such target in the Makefile" for t in missing]
    if program in OTHER_PROGRAMS:
        return []
    return [f"{' '.join(words)}: '{program}' is not checked; check it here or add it to OTHER_PROGRAMS"]


@pytest.mark.parametrize("page, line, body", _params("bash"))
def test_bash_block_commands_are_valid(page, line, body):
    commands = _shell_commands(body)
    assert commands, f"{_where(page, line)}: a ```bash block without a command"
    problems = [p for words in commands for p in _check_command(words)]
    assert not problems, f"{_where(page, line)}:\n" + "\n".join(problems)


@pytest.mark.parametrize(
    "words, expected",
    [
        ("skinid info data.h5", [["info", "data.h5"]]),
        (
            "skinid x --a [--b 1 | --c C] [--d]",
            [
                ["x", "--a", "--b", "1", "--d"],
                ["x", "--a"],
                ["x", "--a", "--d"],
                ["x", "--a", "--c", "1", "--d"],
                ["x", "--a", "--b", "1"],
            ],
        ),
        ("skinid x --s a|b [m.csv ...]", [["x", "--s", "a", "m.csv"], ["x", "--s", "a"], ["x", "--s", "b", "m.csv"]]),
        ("skinid x [--n | --r u|e]", [["x", "--n"], ["x"], ["x", "--r", "u"], ["x", "--r", "e"]]),
    ],
)
def test_synopsis_expansion(words, expected):
    variants, elided = _expansions(shlex.split(words)[1:])
    assert variants == expected and not elided


def test_shell_command_prefixes_and_elision():
    (words,) = _shell_commands("OMP_NUM_THREADS=1 mpirun -n 2 .venv/bin/skinid sweep \\\n  ... --resume  # x\n")
    assert _program(words) == ("skinid", ["sweep", "...", "--resume"])
    assert _expansions(["sweep", "...", "--resume"]) == ([["sweep", "--resume"]], True)
    assert not _check_command(words)
    assert _check_command(["skinid", "infer", "--emulator", "e", "--data", "d", "--out", "o", "--frames", "-3,-2,-1"])
    assert _check_command(["skinid", "study", "noise", "--data", "d", "--design", "2", "--out", "o"])  # deprecated
    assert _check_command(["make", "no-such-target"]) and not _check_command(["make", "test"])
    assert _check_command(["skinid", "sweep", "--config", "no-such-preset", "--out", "d.h5"])
    assert _check_command(["skinid", "sweep", "--conf", "small", "--out", "d.h5"])  # abbreviated


# ---- ```python blocks: executed ----------------------------------------------------------------------


def _run_python_block(page: Path, line: int, body: str, monkeypatch: pytest.MonkeyPatch) -> dict:
    """Execute a block against a copy of the effect registry (undone by ``monkeypatch``); its namespace."""
    from skinfem import effects

    monkeypatch.setattr(effects, "EFFECTS", dict(effects.EFFECTS))
    namespace = {"__name__": "docs_example"}
    exec(compile(body, _where(page, line), "exec"), namespace)
    return namespace


@pytest.mark.parametrize("page, line, body", _params("python"))
def test_python_blocks_run(page, line, body, monkeypatch):
    _run_python_block(page, line, body, monkeypatch)


def test_criticism_overview_effect_example_scales_the_membrane_stiffness(monkeypatch):
    from skinfem import effects
    from skinfem.materials import LaminaStiffness

    page = ROOT / "docs" / "criticism-overview.md"
    ((line, body),) = [(line, body) for p, line, lang, body in BLOCKS if p == page and lang == "python"]
    namespace = _run_python_block(page, line, body, monkeypatch)
    cls = effects.get_effect("membrane_stiffness")
    assert cls is namespace["MembraneStiffness"] and issubclass(cls, effects.Effect)
    assert [q.name for q in cls.parameters] == ["log_factor"] and cls.parameters[0].null == 0.0
    q = LaminaStiffness(Q11=10.0, Q22=5.0, Q12=2.0, Q66=3.0, G13=4.0, G23=6.0, E3=7.0)
    for factor in (1.0, 2.0):  # 1: the null value leaves the membrane unchanged
        terms = effects.ModelTerms(
            skin_map=None, skin_prestretch=None, skin_bulk_ratio=20.0, muscle_mu=0.0035, lamina=q
        )
        cls().apply(terms, {"log_factor": math.log(factor)})
        scaled = terms.lamina
        assert [scaled.Q11, scaled.Q22, scaled.Q12, scaled.Q66] == pytest.approx([factor * v for v in (10, 5, 2, 3)])
        assert (scaled.G13, scaled.G23, scaled.E3) == (4.0, 6.0, 7.0)


# ---- help texts --------------------------------------------------------------------------------------


def _walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(words that select it, parser) of ``parser`` and of all its sub-parsers."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, (*path, name))


def test_help_examples_parse():
    """An option example in a help text (``--frames=-3,-2,-1``) is accepted by its parser."""
    from skinfem.cli import ROUTES

    examples, problems = set(), set()
    for command in ROUTES:
        parser, skip = _command_parser(command)
        prefix = f"skinid {command}" if skip else "skinid"
        for path, sub in _walk(parser):
            for action in sub._actions:
                for example in HELP_EXAMPLE.findall(action.help or ""):
                    argv = [*path, example]
                    examples.add(f"{prefix} {' '.join(argv)}")
                    if said := _parse(_command_parser(command)[0], argv, relaxed=True):
                        problems.add(f"{prefix} {' '.join(argv)}: {said}")
    assert examples, "no option example in the help texts (e.g. --frames=-3,-2,-1)"
    assert not problems, "\n".join(sorted(problems))


# ---- links and command names -------------------------------------------------------------------------


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
    from inference.cli_parsers import build_parser
    from skinfem.cli import ROUTES

    # a command routed to a package must be known there too
    for name, (module, _) in ROUTES.items():
        if module == "inference.__main__":
            assert name in inference_cli.COMMANDS, name
    actions = {
        "surrogate": _subcommands(surrogate_cli.build_parser()),
        "study": _subcommands(build_parser("skinid study")),
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
