"""Figures in the docs, checked against the commands that produce them: ``python -m overhang_framework.docfigures``.

Every figure that README.md and docs/ quote from a command is registered in
``docs/checks/*.yaml``: the command as the docs show it, how to read what it
prints, and for each figure the file, the text the file says and a template
that makes that text from the command's output::

    - name: main-job
      command: python -m overhang_framework          # named in each figure's file, beside the figure
      output: metrics.json                           # or stdout (its last line is one JSON object),
                                                     # or file:NAME (a JSON file the command writes in {out})
      minutes: 1                                     # what a run costs on 2 cores
      figures:
        - file: README.md
          text: terminal reward 1.685 ± 0.078
          template: terminal reward {reward_mean:.3f} ± {reward_sem:.3f}
        - file: README.md
          text: takes about 26 s
          template: takes about {wall_time:.0f} s
          tolerance: 0.5                             # timings: each number within 50% of the command's

With ``output: metrics.json`` the command runs with ``hydra.run.dir`` set to a
fresh directory and the file there is read; ``run:`` gives another command to
run in place of ``command``, with ``{out}`` for that directory (``file:NAME``
needs one: ``--out {out}``, ``hydra.sweep.dir={out}``) and ``{python}`` for this
interpreter (inside a ``bash -c`` of several commands). A template is
Python's ``str.format`` over the output (``{world_stats[cache][hits]}``).

Without ``--run`` (a second): the registry is read and every figure's text and
every command are looked for in their files. With ``--run``: each chosen
command runs and each figure is made again; a figure whose text differs (by
more than its tolerance, where it has one) is reported stale, and the exit
status is 1.

    python -m overhang_framework.docfigures                      # the registry and the texts
    python -m overhang_framework.docfigures --run --minutes 2    # rerun every command of at most 2 min
    python -m overhang_framework.docfigures --run --only main-job
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

from overhang_framework.errors import OverhangError

REGISTRY = Path("docs") / "checks"
OUTPUTS = ("metrics.json", "stdout")
NUMBER = re.compile(r"-?\d[\d,]*(?:\.\d+)?")


class RegistryError(OverhangError):
    """A registry file that is not of the documented form."""


@dataclass
class Figure:
    file: str
    text: str
    template: str
    tolerance: Optional[float] = None


@dataclass
class Entry:
    name: str
    command: str
    output: str
    minutes: float
    figures: list[Figure]
    run: Optional[str] = None
    source: str = ""

    def argv(self, out: Path) -> list[str]:
        """The command to execute, writing into ``out``; ``python`` is this interpreter."""
        if self.run is not None:
            words = shlex.split(self.run.replace("{out}", str(out)).replace("{python}", shlex.quote(sys.executable)))
        else:
            words = shlex.split(self.command)
            if self.output == "metrics.json":
                words.append(f"hydra.run.dir={out}")
        if words and words[0] == "python":
            words[0] = sys.executable
        return words


@dataclass
class Result:
    entry: Entry
    figure: Figure
    made: Optional[str]
    ok: bool
    why: str = ""


@dataclass
class Report:
    results: list[Result] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures and all(r.ok for r in self.results)


def _field(where: str, data: dict, key: str, kind, required: bool = True):
    value = data.get(key)
    if value is None and not required:
        return None
    if isinstance(value, bool) or not isinstance(value, kind):
        names = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
        raise RegistryError(f"{where}: '{key}' must be a {names}, got {value!r}")
    return value


def load_registry(directory: Path = REGISTRY) -> list[Entry]:
    """Every entry of every ``*.yaml`` file in ``directory``; a malformed one raises :class:`RegistryError`."""
    import yaml

    directory = Path(directory)
    files = sorted(directory.glob("*.yaml"))
    if not files:
        raise RegistryError(f"no registry files (*.yaml) in {directory}; run from the repository root")
    entries, names = [], {}
    for path in files:
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as err:
            raise RegistryError(f"{path}: not YAML ({str(err).splitlines()[0]})") from None
        if not isinstance(data, list):
            raise RegistryError(f"{path}: must be a list of entries, got {type(data).__name__}")
        for i, raw in enumerate(data):
            where = f"{path} entry {i + 1}"
            if not isinstance(raw, dict):
                raise RegistryError(f"{where}: must be a mapping, got {raw!r}")
            unknown = set(raw) - {"name", "command", "output", "minutes", "figures", "run"}
            if unknown:
                raise RegistryError(f"{where}: unknown keys {', '.join(sorted(unknown))}; allowed: command, "
                                    f"figures, minutes, name, output, run")
            name = _field(where, raw, "name", str)
            where = f"{path} entry {name!r}"
            if name in names:
                raise RegistryError(f"{where}: the name is taken by an entry of {names[name]}")
            names[name] = path
            output = _field(where, raw, "output", str)
            if output not in OUTPUTS and not (output.startswith("file:") and len(output) > 5):
                raise RegistryError(f"{where}: output must be one of {', '.join(OUTPUTS)} or file:NAME, "
                                    f"got {output!r}")
            if output.startswith("file:") and "{out}" not in str(raw.get("run")):
                raise RegistryError(f"{where}: output {output} needs a 'run' command that writes into {{out}}")
            minutes = _field(where, raw, "minutes", (int, float))
            figures = []
            for j, f in enumerate(_field(where, raw, "figures", list)):
                at = f"{where} figure {j + 1}"
                if not isinstance(f, dict) or set(f) - {"file", "text", "template", "tolerance"}:
                    raise RegistryError(f"{at}: must be a mapping of file, text, template and tolerance")
                tolerance = _field(at, f, "tolerance", (int, float), required=False)
                if tolerance is not None and tolerance < 0:
                    raise RegistryError(f"{at}: tolerance must be >= 0, got {tolerance}")
                figures.append(Figure(_field(at, f, "file", str), _field(at, f, "text", str),
                                      _field(at, f, "template", str), tolerance))
            if not figures:
                raise RegistryError(f"{where}: has no figures")
            entries.append(Entry(name, _field(where, raw, "command", str), output, float(minutes), figures,
                                 _field(where, raw, "run", str, required=False), str(path)))
    return entries


def check_texts(entries: Sequence[Entry], root: Path = Path(".")) -> list[str]:
    """Problems with the docs as they are: a figure's text or its command missing from its file."""
    problems = []
    for entry in entries:
        for figure in entry.figures:
            path = root / figure.file
            if not path.is_file():
                problems.append(f"{entry.name}: {figure.file} does not exist")
                continue
            text = " ".join(path.read_text().split())
            if " ".join(figure.text.split()) not in text:
                problems.append(f"{entry.name}: {figure.file} does not say {figure.text!r}")
            if " ".join(entry.command.split()) not in text:
                problems.append(f"{entry.name}: {figure.file} does not name the command {entry.command!r}")
    return problems


def render(figure: Figure, output: dict) -> str:
    """The figure's text as the command's ``output`` makes it."""
    try:
        return figure.template.format(**output)
    except (KeyError, IndexError, AttributeError, ValueError, TypeError) as err:
        raise RegistryError(f"template {figure.template!r} does not fit the command's output "
                            f"({type(err).__name__}: {err})") from None


def _numbers(text: str) -> list[float]:
    return [float(m.replace(",", "")) for m in NUMBER.findall(text)]


def matches(figure: Figure, made: str) -> tuple[bool, str]:
    """Whether the docs' text agrees with the text the command made, and why not."""
    if figure.tolerance is None:
        return " ".join(made.split()) == " ".join(figure.text.split()), ""
    said, now = _numbers(figure.text), _numbers(made)
    words = NUMBER.sub("#", " ".join(figure.text.split())), NUMBER.sub("#", " ".join(made.split()))
    if len(said) != len(now) or words[0] != words[1]:
        return False, "the words differ"
    for a, b in zip(said, now):
        if abs(a - b) > figure.tolerance * abs(b) + 1e-12:
            return False, f"{a:g} is more than {figure.tolerance:.0%} from {b:g}"
    return True, f"within {figure.tolerance:.0%}"


def command_output(entry: Entry, cwd: Path = Path("."), timeout: Optional[float] = None) -> dict:
    """Run ``entry``'s command in ``cwd`` and read what it printed or wrote, as a dict."""
    with tempfile.TemporaryDirectory(prefix="docfigures-") as tmp:
        out = Path(tmp) / "run"
        out.mkdir()
        argv = entry.argv(out)
        try:
            proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, cwd=cwd)
        except subprocess.TimeoutExpired:
            raise RegistryError(f"{entry.name}: the command took more than {timeout:.0f} s") from None
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
            raise RegistryError(f"{entry.name}: the command failed with status {proc.returncode}: {last}")
        if entry.output == "metrics.json" or entry.output.startswith("file:"):
            name = "metrics.json" if entry.output == "metrics.json" else entry.output[5:]
            try:
                data = json.loads((out / name).read_text())
            except (OSError, ValueError) as err:
                raise RegistryError(f"{entry.name}: cannot read {name} that the command wrote: {err}") from None
            if not isinstance(data, dict):
                raise RegistryError(f"{entry.name}: {name} holds no JSON object")
            return data
        lines = proc.stdout.strip().splitlines()
        try:
            data = json.loads(lines[-1])
        except (IndexError, ValueError):
            raise RegistryError(f"{entry.name}: the command's last line is not one JSON object") from None
        if not isinstance(data, dict):
            raise RegistryError(f"{entry.name}: the command's last line is not one JSON object")
        return data


def run_checks(entries: Sequence[Entry], root: Path = Path("."), log=print) -> Report:
    """Run each entry's command (in ``root``) and compare every figure it makes with the docs."""
    report = Report()
    for entry in entries:
        log(f"{entry.name}: {entry.command} (about {entry.minutes:g} min) ...")
        started = time.monotonic()
        try:
            output = command_output(entry, root)
        except (RegistryError, OSError, ValueError) as err:
            report.failures.append(str(err))
            log(f"  failed: {err}")
            continue
        for figure in entry.figures:
            try:
                made = render(figure, output)
            except RegistryError as err:
                report.failures.append(f"{entry.name}: {err}")
                log(f"  {figure.file}: {err}")
                continue
            ok, why = matches(figure, made)
            report.results.append(Result(entry, figure, made, ok, why))
            state = "ok" if ok else "STALE"
            log(f"  {state:5} {figure.file}: says {figure.text!r}; the command makes {made!r}"
                + (f" ({why})" if why else ""))
        log(f"  ({time.monotonic() - started:.0f} s)")
    return report


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.docfigures",
                                     description="Check the figures in README.md and docs/ against the commands "
                                                 "that produce them (registry: docs/checks/*.yaml).")
    parser.add_argument("--run", action="store_true", help="rerun the commands and compare every figure")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="these entries only")
    parser.add_argument("--minutes", type=float, default=None,
                        help="with --run: only entries whose command takes at most this many minutes")
    parser.add_argument("--registry", type=Path, default=REGISTRY, help="the registry directory (docs/checks)")
    parser.add_argument("--list", action="store_true", help="list the entries and their cost, then stop")
    args = parser.parse_args(argv)
    try:
        entries = load_registry(args.registry)
    except RegistryError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.only:
        unknown = sorted(set(args.only) - {e.name for e in entries})
        if unknown:
            print(f"error: no entry named {', '.join(unknown)}; entries: {', '.join(e.name for e in entries)}",
                  file=sys.stderr)
            return 2
        entries = [e for e in entries if e.name in args.only]
    if args.list:
        for e in entries:
            print(f"{e.name:28} {e.minutes:6g} min  {len(e.figures):3} figures  {e.command}")
        return 0
    root = args.registry.resolve().parents[1]
    problems = check_texts(entries, root)
    for p in problems:
        print(f"missing: {p}")
    print(f"{sum(len(e.figures) for e in entries)} figures from {len(entries)} commands; "
          f"{len(problems)} not found in their files")
    if not args.run:
        return 1 if problems else 0
    chosen = [e for e in entries if args.minutes is None or e.minutes <= args.minutes]
    report = run_checks(chosen, root)
    stale = [r for r in report.results if not r.ok]
    print(f"{len(report.results) - len(stale)} figures agree, {len(stale)} stale, "
          f"{len(report.failures)} could not be made, over {len(chosen)} commands")
    return 0 if report.ok and not problems else 1


if __name__ == "__main__":
    sys.exit(main())
