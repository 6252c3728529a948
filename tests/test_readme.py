"""The README's mechanical claims against the code: every configuration key, `PIPELINE__` variable,
`make` target, `pipeline` command and option, Python name and link it names exists.

A renamed key, option or target, or a moved section, makes a new user's copied command fail; these
checks keep the README's names in step with the code (the figures it reports are not checked)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import click

from pipeline.cli import main
from pipeline.config import all_keys

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
MAKEFILE = (ROOT / "Makefile").read_text(encoding="utf-8")
KEYS = set(all_keys())
SECTIONS = {key.split(".")[0] for key in KEYS}
FILE_SUFFIXES = {"zarr", "py", "txt", "json", "md", "npy", "safetensors", "png", "pcd", "bin", "toml", "jpg"}


def code_spans(text: str) -> list[str]:
    """Inline `code` spans and the lines of ``` blocks."""
    blocks = re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S)
    rest = re.sub(r"```[a-z]*\n.*?```", "", text, flags=re.S)
    inline = [re.sub(r"\s*\n\s*", " ", span) for span in re.findall(r"`([^`]+)`", rest) if "\n\n" not in span]
    return [line for block in blocks for line in block.splitlines()] + inline


def named_keys(spans: list[str]) -> set[str]:
    """section.key names in the spans (a trailing * stands for any key of that prefix)."""
    found = set()
    for span in spans:
        for section, name in re.findall(r"(?<![\w./-])([a-z]+)\.([A-Za-z_0-9]+\*?)(?![\w/])", span):
            if section in SECTIONS and name not in FILE_SUFFIXES:
                found.add(f"{section}.{name}")
    return found


def test_every_configuration_key_the_readme_and_makefile_name_exists():
    names = named_keys(code_spans(README)) | named_keys(re.findall(r"--set (\S+)=", MAKEFILE))
    assert len(names) > 30  # the README names many keys: the pattern still finds them
    missing = sorted(name for name in names
                     if not (name in KEYS or name.endswith("*") and any(k.startswith(name[:-1]) for k in KEYS)))
    assert not missing, f"README/Makefile name configuration keys that do not exist: {missing}"


def test_every_pipeline_variable_the_readme_names_is_a_key():
    variables = set(re.findall(r"\bPIPELINE__([A-Z0-9_]+?)__([A-Z0-9_]+)", README)) - {("SECTION", "KEY")}
    assert variables
    missing = sorted(f"PIPELINE__{s}__{k}" for s, k in variables if f"{s.lower()}.{k.lower()}" not in
                     {key.lower() for key in KEYS})
    assert not missing, f"README names PIPELINE__ variables of no key: {missing}"


def make_targets() -> set[str]:
    targets = set()
    for line in MAKEFILE.splitlines():
        match = re.match(r"^([A-Za-z$][\w.$()/ -]*):(?!=)", line)
        if match:
            targets.update(match.group(1).split())
    stages = re.search(r"^STAGES :?= (.+)$", MAKEFILE, flags=re.M).group(1).split()
    return (targets - {"$(STAGES)"}) | set(stages)


def test_every_make_target_the_readme_names_exists():
    named = {target for span in code_spans(README) for target in re.findall(r"(?:^|\s)make ([a-z][\w-]*)", span)}
    assert {"demo", "test"} <= named
    missing = sorted(named - make_targets())
    assert not missing, f"README names make targets the Makefile lacks: {missing}"


def test_every_pipeline_command_and_option_the_readme_names_exists():
    commands = main.commands
    problems = []
    for span in code_spans(README):
        span = re.sub(r"\s#.*$", "", span)  # a shell comment
        for match in re.finditer(r"(?:^|[\s/`])pipeline ([a-z][\w-]*)((?:[^|]*))", span):
            name, rest = match.group(1), match.group(2)
            if name not in commands:
                problems.append(f"`pipeline {name}`: no such command")
                continue
            options = {opt for param in commands[name].params if isinstance(param, click.Option)
                       for opt in param.opts + param.secondary_opts}
            problems += [f"`pipeline {name} {opt}`: no such option" for opt in re.findall(r"(?<!\w)--[a-z][\w-]*", rest)
                         if opt not in options | {"--help"}]
    assert not problems, "README: " + "; ".join(problems)


OTHER_TOOLS_OPTIONS = {"--kills", "--data", "--dist"}
"""Options the README gives to other programs: `python -m tests.soak --kills`, `python -m
pipeline.readers.figure --data`, pytest-xdist's `--dist`."""


def test_every_option_the_readme_names_is_a_pipeline_option():
    options = {opt for command in main.commands.values() for param in command.params
               if isinstance(param, click.Option) for opt in param.opts + param.secondary_opts}
    named = {opt for span in code_spans(README) for opt in re.findall(r"(?<![\w-])--[a-z][\w-]*", span)}
    assert "--dry-run" in named
    missing = sorted(named - options - OTHER_TOOLS_OPTIONS - {"--help"})
    assert not missing, f"README names options no pipeline command has: {missing}"


def test_every_python_name_the_readme_names_exists():
    names = {span for span in re.findall(r"`([^`\n]+)`", README) if re.fullmatch(r"(?:pipeline|stages)(?:\.\w+)+", span)}
    assert names
    missing = []
    for name in sorted(names):
        parts = name.split(".")
        for cut in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
                break
            except ImportError:
                continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr, None)
        if obj is None:
            missing.append(name)
    assert not missing, f"README names Python objects that do not exist: {missing}"


def github_anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def link_problems(doc: Path) -> list[str]:
    """Links of ``doc`` (a Markdown file of the repository) to a file that does not exist, or to a
    heading (``#anchor``, ``file.md#anchor``) that file does not have; relative to ``doc``'s folder."""
    text = doc.read_text(encoding="utf-8")
    problems = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if target.startswith(("http://", "https://")):
            continue
        path, _, anchor = target.partition("#")
        linked = (doc.parent / path).resolve() if path else doc
        if not linked.exists():
            problems.append(f"{doc.name}: {target}: no such file")
        elif anchor and linked.suffix == ".md":
            headings = re.findall(r"^#+ (.+)$", linked.read_text(encoding="utf-8"), flags=re.M)
            if anchor not in {github_anchor(h) for h in headings}:
                problems.append(f"{doc.name}: {target}: no such heading")
    return problems


def test_every_link_of_the_readme_and_docs_resolves():
    """README.md's links and those of docs/*.md (the measurement record and the README's history),
    headings included: a moved or renamed section breaks a link a reader follows."""
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    assert len(docs) >= 3
    problems = [problem for doc in docs for problem in link_problems(doc)]
    assert not problems, "links: " + "; ".join(problems)
