"""Every option an error message suggests exists on the command that printed it (issue 44).

The test walks the messages statically: every call of ``InputError``/``ArtifactError``, click's
``UsageError``/``BadParameter``/``BadOptionUsage``/``ClickException``, ``.error(...)`` (argparse, a log),
``.fail(...)`` and ``exit(...)``/``SystemExit(...)`` in the project's packages (pyproject's
``packages.find``), and collects the options each suggests: the ``--flag``s in its string constants
and f-string parts (a module-level string constant it names included), and the flags of the
:class:`pipeline.runtime.errors.Option` objects it passes (on the command line they are spelled as flags).

Who can print a message: the ``geodistill`` commands (the click group of pyproject's console script,
every subcommand) and the project's own scripts (``python -m pkg.mod`` with their own argparse or
click options) whose static import closure holds the message's module.  A command whose module imports
one that runs ``dvc repro`` and raises a stage's error line as its own (``InputError.from_line``:
``distill``) also prints the messages of the modules only the DAG's stages reach.

The rule, per suggested flag:

* after ``geodistill NAME`` (or ``python -m MODULE``) in the same string, the flag must be an option of
  that command (or script); a backtick span that starts with another program (`dvc ...`) is not ours;
* a message in a command's own module (where the click command is defined) is that command's: the
  flag must be one of its options;
* any other message: the flag must be an option of at least one command that can print it;
* and a message that such a DAG runner prints through a stage (a module the stages reach and no other
  user command does) needs the flag on the runner too -- unless the DAG itself passes it to the stage
  (dvc.yaml's ``cmd``: plumbing the user never types).  This is what catches ``distill`` suggesting
  export's ``--no-int8``.

``Option`` objects are rendered as keywords for Python callers, so a message only the Python API
reaches is checked for its literal flags only.  The import closure is static (function-level imports
included), so "can print" over-approximates; hence "at least one" rather than "every".
"""

from __future__ import annotations

import ast
import functools
import importlib
import re
import sys
import tomllib
from pathlib import Path

import click
import yaml

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PACKAGES = tuple(p.rstrip("*") for p in PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"])
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: the calls whose string arguments are an error message a person reads
MESSAGE_CALLS = {"InputError", "ArtifactError", "UsageError", "BadParameter", "BadOptionUsage", "ClickException",
                 "error", "fail", "exit", "SystemExit"}
#: a command or script named in a message, and the text it governs (to the end of its backtick span)
NAMED = re.compile(r"(?:geodistill ((?:[a-z][a-z-]*)(?: [a-z][a-z-]*)?)|python3? -m ([\w.]+))([^`]*)")


# --------------------------------------------------------------------------------------------------
# modules, their imports and their messages (static)
# --------------------------------------------------------------------------------------------------
def module_file(mod: str) -> Path | None:
    for p in (ROOT / (mod.replace(".", "/") + ".py"), ROOT / mod.replace(".", "/") / "__init__.py"):
        if p.is_file():
            return p
    return None


def project_modules() -> list[str]:
    out = []
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = p.relative_to(ROOT).with_suffix("").parts
            out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


@functools.cache
def tree(mod: str) -> ast.Module:
    return ast.parse(module_file(mod).read_text())


@functools.cache
def imports(mod: str) -> dict[str, tuple[str, str]]:
    """{name bound here: (module, name there)} of ``from X import Y`` and the project modules imported."""
    path = module_file(mod)
    pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    bound: dict[str, tuple[str, str]] = {}
    for n in ast.walk(tree(mod)):
        if isinstance(n, ast.Import):
            for a in n.names:
                bound[f"import {a.name}"] = (a.name, "")
        elif isinstance(n, ast.ImportFrom):
            base = n.module or ""
            if n.level:
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - n.level + 1] + ([base] if base else []))
            for a in n.names:
                bound[a.asname or a.name] = (base, a.name)
    return bound


@functools.cache
def imported_modules(mod: str) -> frozenset[str]:
    out = set()
    for base, name in imports(mod).values():
        for m in (base, f"{base}.{name}" if name else base):
            parts = m.split(".")
            out |= {".".join(parts[:i]) for i in range(1, len(parts) + 1)}
    return frozenset(m for m in out if m.split(".")[0] in PACKAGES and module_file(m))


@functools.cache
def closure(mod: str) -> frozenset[str]:
    seen, todo = set(), [mod]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo += imported_modules(m)
    return frozenset(seen)


@functools.cache
def string_constants(mod: str) -> dict[str, tuple[str, ...]]:
    """{module-level name: the string parts of its value}."""
    out = {}
    for n in tree(mod).body:
        if isinstance(n, (ast.Assign, ast.AnnAssign)) and n.value is not None:
            parts = tuple(c.value for c in ast.walk(n.value) if isinstance(c, ast.Constant) and isinstance(c.value, str))
            for t in (n.targets if isinstance(n, ast.Assign) else [n.target]):
                if isinstance(t, ast.Name) and parts:
                    out[t.id] = parts
    return out


@functools.cache
def option_flags(mod: str) -> dict[str, str]:
    """{module-level name: flag} of the ``Option("--flag", ...)`` objects defined in ``mod``."""
    out = {}
    for n in tree(mod).body:
        if (isinstance(n, ast.Assign) and isinstance(n.value, ast.Call) and getattr(n.value.func, "id", "") == "Option"
                and n.value.args and isinstance(n.value.args[0], ast.Constant)):
            for t in n.targets:
                if isinstance(t, ast.Name) and str(n.value.args[0].value).startswith("--"):
                    out[t.id] = n.value.args[0].value
    return out


def resolve(mod: str, name: str, table) -> object | None:
    """``table(module)[name]`` for a name defined in ``mod`` or imported into it from the project."""
    for _ in range(5):
        if name in table(mod):
            return table(mod)[name]
        if name not in imports(mod) or not module_file(imports(mod)[name][0]):
            return None
        mod, name = imports(mod)[name]
    return None


def messages(mod: str):
    """(line, [string parts], {flags of Option objects}) of every message call in ``mod``."""
    for n in ast.walk(tree(mod)):
        if not isinstance(n, ast.Call):
            continue
        f = n.func
        if (f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)) not in MESSAGE_CALLS:
            continue
        strings = [c.value for c in ast.walk(n) if isinstance(c, ast.Constant) and isinstance(c.value, str)]
        options = set()
        for name in {x.id for x in ast.walk(n) if isinstance(x, ast.Name)}:
            strings += list(resolve(mod, name, string_constants) or ())
            if (flag := resolve(mod, name, option_flags)) is not None:
                options.add(flag)
        yield n.lineno, strings, options


# --------------------------------------------------------------------------------------------------
# who prints them: the geodistill commands and the project's own scripts
# --------------------------------------------------------------------------------------------------
def defining_module(cmd: click.Command) -> str:
    """The project module where ``cmd`` is a module-level name (the command's own module)."""
    for name, m in sorted(sys.modules.items()):
        if name.split(".")[0] in PACKAGES and any(v is cmd for v in vars(m).values()):
            return name
    raise AssertionError(f"no module defines {cmd.name}")


def geodistill_commands() -> dict[str, tuple[str, frozenset[str]]]:
    """{"review export": (its module, its options)} of every leaf command of the console script."""
    mod, _, attr = PYPROJECT["project"]["scripts"]["geodistill"].partition(":")
    group = getattr(importlib.import_module(mod), attr)
    out = {}

    def walk(cmd, path, inherited, ctx):
        opts = inherited | {o for p in cmd.params for o in (*p.opts, *p.secondary_opts) if o.startswith("--")}
        if isinstance(cmd, click.Group):
            sub = click.Context(cmd, parent=ctx)
            for n in cmd.list_commands(sub):
                walk(cmd.get_command(sub, n), [*path, n], opts, sub)
        else:
            out[" ".join(path)] = (defining_module(cmd), frozenset(opts | {"--help"}))

    ctx = click.Context(group)
    for n in group.list_commands(ctx):
        walk(group.get_command(ctx, n), [n], frozenset(), ctx)
    return out


def script_options(mod: str) -> frozenset[str] | None:
    """The options of ``python -m mod`` (argparse ``add_argument`` / ``click.option`` flags in the
    module, and the keywords of a ``benchmarks.common.parser(...)`` call), None when it is not a script with
    options of its own."""
    t = tree(mod)
    is_main = any(isinstance(n, ast.If) and "__main__" in ast.unparse(n.test) for n in t.body)
    flags = {c.value for n in ast.walk(t) if isinstance(n, ast.Call)
             and (n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", "")) in
             ("add_argument", "option") for c in n.args if isinstance(c, ast.Constant) and str(c.value).startswith("--")}
    flags |= {f"--{k.arg.replace('_', '-')}" for n in ast.walk(t) if isinstance(n, ast.Call)  # benchmarks.common.parser
              and getattr(n.func, "id", getattr(n.func, "attr", "")) == "parser" for k in n.keywords if k.arg}
    return frozenset(flags | {"--help"}) if is_main and flags else None


def dag_plumbing() -> frozenset[str]:
    """The flags dvc.yaml's stage commands pass (every optional stage on)."""
    from pipeline.orchestration.dag import OPTIONAL_STAGES, render_dvc_yaml

    doc = yaml.safe_load(render_dvc_yaml(optional=tuple(OPTIONAL_STAGES)))
    return frozenset(FLAG.findall(str(doc["stages"])))


def split_named(text: str):
    """(command or script named, the text it governs) spans of ``text``, then (None, the rest) with the
    backtick spans of other programs removed."""
    spans = []
    for m in NAMED.finditer(text):
        spans.append((("geodistill", m.group(1)) if m.group(1) else ("python", m.group(2)), m.group(3)))
        text = text.replace(m.group(0), " ", 1)
    rest = re.sub(r"`(?!-)[^`]*`", " ", text)   # `dvc repro --force`, `pip install ...`: another program's
    return spans, rest


# --------------------------------------------------------------------------------------------------
def relays_stages(mod: str) -> bool:
    """Whether ``mod`` runs ``dvc repro`` (names the string "repro") and raises a stage's error line as its
    own (``InputError.from_line``): its command prints the stages' messages without naming the stage."""
    nodes = list(ast.walk(tree(mod)))
    return (any(isinstance(x, ast.Constant) and x.value == "repro" for x in nodes)
            and any(isinstance(x, ast.Attribute) and x.attr == "from_line" for x in nodes))


def problems() -> list[str]:
    """One line per suggested option that breaks the module docstring's rule."""
    from pipeline.orchestration.dag import stage_modules

    commands = geodistill_commands()
    modules = project_modules()
    scripts = {m: o for m in modules if (o := script_options(m)) is not None
               and m not in {mod for mod, _ in commands.values()}}
    reach = {c: closure(m) for c, (m, _) in commands.items()}
    runners = {c for c, (m, _) in commands.items() if any(relays_stages(x) for x in {m, *imported_modules(m)})}
    stage_commands = {c for c, (m, _) in commands.items() if m in set(stage_modules().values())}
    staged = frozenset().union(*(reach[c] for c in stage_commands))
    # reached by a command that is neither a stage nor a runner: a user command's message, not a stage's
    tools = frozenset().union(*(reach[c] for c in set(commands) - stage_commands - runners))
    plumbing = dag_plumbing()
    own: dict[str, set[str]] = {}
    for c, (m, _) in commands.items():
        own.setdefault(m, set()).add(c)
    # the case is in reach: distill prints the export stage's messages as its own
    export_module = commands["export"][0]
    assert "distill" in runners and export_module in staged - tools and export_module not in reach["distill"]
    found = []
    for mod in modules:
        direct = {c for c, cl in reach.items() if mod in cl}
        relayed = {r for r in runners if mod in staged and mod not in tools} - direct
        printers = own.get(mod) or (direct | relayed)
        script_printers = {s for s in scripts if mod in closure(s)}
        for line, strings, option_objs in messages(mod):
            where = f"{module_file(mod).relative_to(ROOT)}:{line}"
            literal = set()
            for s in strings:
                spans, rest = split_named(s)
                for (kind, name), text in spans:
                    if kind == "geodistill" and name not in commands and " " in name:  # "label with ...": no sub
                        name, word = name.split(" ", 1)
                        text = f"{word}{text}"
                    opts = commands.get(name, (None, None))[1] if kind == "geodistill" else (
                        script_options(name) if module_file(name) else None)
                    found += [f"{where}: {flag} is not an option of {kind} {name}" for flag in FLAG.findall(text)
                              if opts is None or flag not in opts]
                literal |= set(FLAG.findall(rest))
            for flag in sorted(literal | option_objs):
                if flag not in literal and not printers:
                    continue  # an Option only the Python API reaches reads as a keyword there
                able = ({c for c in printers if flag in commands[c][1]}
                        | {s for s in script_printers if flag in scripts[s]})
                if not able:
                    found.append(f"{where}: {flag} is an option of none of {sorted(printers | script_printers)}")
                found += [f"{where}: geodistill {r} prints this stage message and has no {flag}"
                          for r in sorted(relayed) if flag not in commands[r][1] and flag not in plumbing]
    return found


def test_every_option_a_message_suggests_exists_on_a_command_that_prints_it():
    found = problems()
    assert not found, "\n".join(found)


def test_the_walk_catches_an_option_the_printing_command_lacks(monkeypatch):
    """Planted messages: export's stage suggesting --no-int8 (distill prints it), segment suggesting a
    flag it lacks -- both caught; a flag after `geodistill export` and another program's are not."""
    real = messages
    segment, distill, export = (geodistill_commands()[c][0] for c in ("segment", "distill", "export"))
    planted = {export: "the int8 model misses its gate; pass --no-int8",
               segment: "try --no-such-option",
               distill: "see `geodistill export --no-int8` or `dvc repro --force`"}

    def with_planted(mod):
        yield from real(mod)
        if mod in planted:
            yield 0, [planted[mod]], set()

    monkeypatch.setattr(sys.modules[__name__], "messages", with_planted)
    found = [f for f in problems() if f.split(":")[1] == "0"]
    assert sorted(found) == sorted([f"{module_file(export).relative_to(ROOT)}:0: geodistill distill prints this "
                                    f"stage message and has no --no-int8",
                                    f"{module_file(segment).relative_to(ROOT)}:0: --no-such-option is an option of "
                                    f"none of ['segment']"]), found
