"""Every shell command of docs/people.md and docs/experiment.md works as written, from the repository's root.

The commands are read from the docs' shell blocks (```bash, ```sh, ```shell, ```console, and an unlabelled block
that opens with a command): continuation lines joined, comments dropped, ``&&`` and ``;`` chains split. ``TABLE``
classifies each one, and fails when the docs gain a command it does not classify or lose one it names:

* ``run``: done in seconds; each doc's run in its order (a later command reads what an earlier one wrote) in a
  directory that mirrors the repository's root (its files linked, ``runs/`` its own), so what a command writes
  goes there and never into the checkout. docs/experiment.md's study commands (export, reissue, withdraw) read a
  small study database the test prepares where the docs' server would have made it.
* ``slow``: done in ten seconds or more; run among the slow tests (``pytest -m slow``, after the ``run`` commands
  before it), validated otherwise.
* ``validate``: too long to run here (simulations, fits, servers); the command's own parser reads its arguments
  and its own checks compose its config with the overrides it passes, as it does before it starts, so a
  misspelt key, an unknown config name or a refused value fails here.
* ``env``: ``export NAME=VALUE``, the environment of the doc's later commands.
* anything else: the reason the command is neither run nor validated.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from commands import run_chains

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("docs/people.md", "docs/experiment.md")
SHELL = {"bash", "sh", "shell", "console"}
OURS = re.compile(r"python -m overhang_framework[\w.]*(?: |$)")

LONG_SIM = "a simulation of participants: minutes to hours"
# (a regular expression the whole command matches, what is done with it, why a command not run is not)
TABLE: list[tuple[str, str, str]] = [
    # docs/people.md: the kept fits, runs and figures, read again
    (r"python -m overhang_framework\.fit\.marginal --recovery docs/\S+ \S+( --against docs/\S+)?", "run", ""),
    (r"python -m overhang_framework\.fit\.adequacy --table docs/\S+", "run", ""),
    (r"python -m overhang_framework\.graded docs/\S+\.csv", "run", ""),
    (r"python -m overhang_framework\.graded( --fits docs/\S+)+ --resamples 0", "run", ""),
    (r"mkdir -p runs/paper_cohort", "run", ""),
    (r"tar xzf docs/simulations/paper-fit-d123/cohort\.tar\.gz -C runs/paper_cohort", "run", ""),
    (r"python -m overhang_framework\.behaviour\.calibrate measure docs/simulations/\S+\.csv", "run", ""),
    # docs/people.md: what makes them
    (r"python -m overhang_framework\.participants .*", "validate", LONG_SIM),
    (r"python -m overhang_framework\.behaviour\.calibrate (measure|library) runs/\S+( --out \S+)?", "validate",
     "reads the participants run before it"),
    (r"python -m overhang_framework\.behaviour\.calibrate fit runs/.*", "validate",
     "an ABC fit of the library before it: about a minute"),
    (r"python -m overhang_framework\.study .*", "validate", "a study: simulations and fits, minutes to hours"),
    (r"python -m overhang_framework\.fit\.recovery .*", "validate", "a recovery of 81 participants: hours"),
    (r"python -m overhang_framework\.fit runs/.*", "validate", "a fit of the run before it: minutes to hours"),
    (r"python -m overhang_framework\.experiment serve .*", "validate", "a server: it runs until stopped"),
    (r"python -m overhang_framework\.experiment pilot .*", "validate", "a pilot through a server: minutes"),
    (r"python -m overhang_framework\.experiment export --out runs/graded-export\.jsonl", "validate",
     "reads the graded study's database of people"),
    # docs/experiment.md: running a study
    (r"export OVERHANG_ADMIN_TOKEN=\S+", "env", ""),
    (r"python -m overhang_framework\.experiment( port=\d+ run_dir=\S+| database=\S+)?", "validate",
     "a server: it runs until stopped"),
    (r"python -m overhang_framework\.experiment export .*run_dir=runs/pilot.*", "run", ""),
    (r"python -m overhang_framework\.experiment (reissue|withdraw) P1( --yes)? run_dir=runs/pilot", "run", ""),
    (r"python -m overhang_framework\.analyze runs/pilot/(log\.jsonl|dataset) --out runs/pilot/analysis", "slow",
     "an analysis of the prepared study: about 10 s each"),
    (r"python -m overhang_framework\.behaviour\.psychds runs/pilot/dataset", "run", ""),
    (r"python -m overhang_framework\.experiment\.practice", "run", ""),
    (r"python -m overhang_framework\.experiment\.practice practice\.tolerance=\S+ --out \S+", "slow",
     "searches the three practice towers anew: about a minute"),
    (r"python -m overhang_framework\.bench\.pilot_recovery .*", "validate",
     "a pilot, a simulation and two fits: minutes"),
]


@dataclass(frozen=True)
class Command:
    doc: str
    line: int  # the line of its block's opening fence
    text: str

    def __str__(self):
        return f"{self.doc}:{self.line}: {self.text}"


def split_line(line: str) -> list[str]:
    """The commands of one shell line: split at ``&&`` and ``;`` outside quotes, a comment cut off, spaces
    collapsed."""
    parts, current, quote, i = [], "", None, 0
    while i < len(line):
        c = line[i]
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "#" and (not current or current[-1].isspace()):
            break
        elif line.startswith("&&", i) or c == ";":
            parts.append(current)
            current, i = "", i + (2 if c == "&" else 1)
            continue
        current += c
        i += 1
    parts.append(current)
    return [" ".join(p.split()) for p in parts if p.strip()]


def doc_commands(doc: str) -> list[Command]:
    """The commands of ``doc``'s shell blocks, in their order."""
    text = (ROOT / doc).read_text()
    out = []
    for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, flags=re.S | re.M):
        lang, body = m.group(1), m.group(2)
        if lang not in SHELL and not (lang == "" and re.match(r"(\$ |python )", body)):
            continue  # output, a config, an error message
        line = text[:m.start()].count("\n") + 1
        for row in body.replace("\\\n", " ").splitlines():
            row = row[2:] if row.startswith("$ ") else row
            out += [Command(doc, line, c) for c in split_line(row)]
    return out


def all_commands() -> list[Command]:
    return [c for doc in DOCS for c in doc_commands(doc)]


def action(command: Command) -> tuple[str, str]:
    """``TABLE``'s action and reason for ``command`` (the first entry that matches it)."""
    for pattern, what, why in TABLE:
        if re.fullmatch(pattern, command.text):
            return what, why
    raise LookupError(str(command))


def test_the_docs_shell_blocks_are_read():
    commands = all_commands()
    assert len(commands) > 50
    assert sum(1 for c in commands if OURS.match(c.text)) > 50
    assert any(c.text.startswith("python -m overhang_framework.study graded_budgets --out runs/graded --sim "
                                 "runs/graded_new --sim runs/pp_tl") for c in commands), "continuations joined"
    assert split_line("mkdir -p a && tar xzf b -C a  # unpack") == ["mkdir -p a", "tar xzf b -C a"]
    assert split_line("python -m x 'a; b' \"c # d\" # e; f") == ["python -m x 'a; b' \"c # d\""]


def test_the_table_classifies_every_command_and_names_only_commands_the_docs_have():
    commands = all_commands()
    unclassified = []
    for c in commands:
        try:
            action(c)
        except LookupError:
            unclassified.append(str(c))
    assert not unclassified, "commands the docs gained; classify them in TABLE: " + "\n".join(unclassified)
    stale = [p for p, _, _ in TABLE if not any(re.fullmatch(p, c.text) for c in commands)]
    assert not stale, f"TABLE names commands the docs no longer have: {stale}"
    for pattern, what, why in TABLE:
        assert what in ("run", "slow", "validate", "env") or (what and not why), (pattern, what)
        assert what not in ("slow", "validate") or why, f"say why {pattern} is not run"
    # a command that is not ours is run only when a command of ours needs what it does
    others = [c for c in commands if not OURS.match(c.text)]
    assert {c.text.split()[0] for c in others} <= {"mkdir", "tar", "export"}, others


# -- running ---------------------------------------------------------------------------------------------------
def mirror(dest: Path) -> Path:
    """A directory standing in for the repository's root: its entries linked, without its runs and outputs."""
    dest.mkdir(parents=True)
    for entry in ROOT.iterdir():
        if entry.name not in {"runs", "outputs", ".git", ".venv", ".pytest_cache"}:
            (dest / entry.name).symlink_to(entry)
    return dest


def doc_env(doc: str) -> dict[str, str]:
    """The environment a reader has after the doc's ``export NAME=VALUE`` lines."""
    env = {}
    for c in doc_commands(doc):
        if action(c)[0] == "env":
            name, _, value = c.text.split(" ", 1)[1].partition("=")
            env[name] = shlex.split(value)[0]
    return env


def prepared_study(root: Path) -> None:
    """A study of two participants, P1 and P2, two main trials each, in ``root/runs/pilot`` (the run_dir of
    docs/experiment.md's server), made through the server's API."""
    from test_experiment_ops import client_for, play

    (root / "runs" / "pilot").mkdir(parents=True)
    client = client_for([f"run_dir={root / 'runs' / 'pilot'}", "admin_token=a-prepared-admin-token",
                         "physics_processes=0"])
    play(client, "P1", main_trials=2)
    play(client, "P2", main_trials=2)
    client.store.close()


def tracked_changes() -> str:
    if not (ROOT / ".git").exists():
        return ""
    return subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                          text=True).stdout


def run_docs(tmp_path: Path, kinds: tuple[str, ...]) -> list[tuple[Command, subprocess.CompletedProcess]]:
    """The commands of each doc whose action is one of ``kinds``, in its order (an identical command once), each
    doc in its own mirror of the root; the two docs at once."""
    chains, cwds, envs, done = [], [], [], []
    for doc in DOCS:
        seen, commands = set(), []
        for c in doc_commands(doc):
            if action(c)[0] in kinds and c.text not in seen:
                seen.add(c.text)
                commands.append(c)
        root = mirror(tmp_path / Path(doc).stem)
        if doc == "docs/experiment.md":
            prepared_study(root)
        env = {**os.environ, **doc_env(doc)}
        env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"  # `python` is this one
        chains.append([["bash", "-c", c.text] for c in commands])
        cwds.append(root)
        envs.append(env)
        done.append(commands)
    before = tracked_changes()
    results = run_chains(chains, timeout=600, envs=envs, cwds=cwds)
    assert tracked_changes() == before, "a doc command wrote into the checkout"
    return [pair for cs, ps in zip(done, results) for pair in zip(cs, ps)]


def failures(pairs) -> list[str]:
    return [f"{c} -> exit {p.returncode}\n{p.stderr[-1500:]}" for c, p in pairs
            if p.returncode != 0 or "Traceback" in p.stderr]


def test_the_commands_that_take_seconds_run_as_written(tmp_path):
    pairs = run_docs(tmp_path, ("run",))
    assert len(pairs) >= 20
    assert not failures(pairs), "\n\n".join(failures(pairs))
    said = {c.text: p.stdout + p.stderr for c, p in pairs}
    assert "a valid Psych-DS dataset" in said["python -m overhang_framework.behaviour.psychds runs/pilot/dataset"]
    assert "withdrew participant P1" in said[
        "python -m overhang_framework.experiment withdraw P1 --yes run_dir=runs/pilot"]
    assert (tmp_path / "people" / "runs" / "paper_cohort" / "participants.csv").is_file()


@pytest.mark.slow
def test_the_commands_that_take_longer_run_as_written(tmp_path):
    pairs = run_docs(tmp_path, ("run", "slow"))
    assert any(action(c)[0] == "slow" for c, _ in pairs)
    assert not failures(pairs), "\n\n".join(failures(pairs))


# -- validating ------------------------------------------------------------------------------------------------
def check_fit(args: list[str]) -> None:
    """``python -m overhang_framework.fit ARGS`` checked as its preflight does, its logs not read (they are what
    the commands before it make)."""
    from overhang_framework.fit.__main__ import CONFIG_NAME, check_settings, command_words
    from overhang_framework.preflight import check_flags, compose_checked, split_flags, sweep_variants

    words = command_words(args)
    check_flags(words)
    flags, overrides = split_flags(words)
    for variant in sweep_variants(overrides, "-m" in flags or "--multirun" in flags):
        check_settings(compose_checked(variant, config_name=CONFIG_NAME))


def check_experiment(args: list[str]) -> None:
    from overhang_framework.experiment import pilot
    from overhang_framework.experiment.__main__ import SUMMARIES, parser
    from overhang_framework.experiment.settings import load_settings

    command = args[0] if args and args[0] in SUMMARIES else "serve"
    args = args[1:] if args and args[0] == command else args
    if command == "pilot":
        pilot.check(pilot.parser().parse_args(args))
        return
    parsed = parser(command).parse_intermixed_args(args)
    load_settings(parsed.overrides, need_admin_token=command == "serve")


def check_study(args: list[str]) -> None:
    from overhang_framework.studies.command import parser
    from overhang_framework.studies.run import check_settings

    a = parser().parse_args(args)
    check_settings(a.study, Path(a.out), a.scale, a.pool, a.tasks, a.jobs, [int(d) for d in a.depths.split(",")],
                   a.resamples, a.replicas, a.seed, a.world, a.participants, a.fit, not a.no_progress, a.sim, a.log)


def check_calibrate(args: list[str]) -> None:
    from overhang_framework.behaviour.calibrate import parser, proposal_distributions

    a = parser().parse_args(args)
    if a.command == "fit":
        proposal_distributions(a.proposal)  # the cohort the library was drawn from


def check_pilot_recovery(args: list[str]) -> None:
    from overhang_framework.bench.pilot_recovery import parser
    from overhang_framework.experiment import pilot

    a = parser().parse_args(args)
    pilot.check(pilot.parser().parse_args(["--out", str(a.out / "pilot"), "--time-scale", a.time_scale,
                                           *[w for s in a.serve for w in ("--serve", s)], *a.overrides]))
    check_fit([str(a.out / "pilot" / "log.jsonl"), "--out", str(a.out / "fit_exported"), *a.fit, "progress=false"])


def check_recovery(args: list[str]) -> None:
    from overhang_framework.fit.recovery import checked_config

    checked_config(args)


def check_participants(args: list[str]) -> None:
    from overhang_framework.behaviour.simulation import preflight

    preflight(args)


def check_practice(args: list[str]) -> None:
    from overhang_framework.experiment.practice import _world_and_tasks, parser

    _world_and_tasks(parser().parse_args(args).overrides)


def check_analyze(args: list[str]) -> None:
    from overhang_framework.analyze import parser

    parser().parse_args(args)  # its input is the export before it


#: How each module's command is checked without running it.
CHECKS = {
    "overhang_framework.participants": check_participants,
    "overhang_framework.behaviour.calibrate": check_calibrate,
    "overhang_framework.study": check_study,
    "overhang_framework.fit": check_fit,
    "overhang_framework.fit.recovery": check_recovery,
    "overhang_framework.experiment": check_experiment,
    "overhang_framework.experiment.practice": check_practice,
    "overhang_framework.analyze": check_analyze,
    "overhang_framework.bench.pilot_recovery": check_pilot_recovery,
}


def validated() -> list[Command]:
    return [c for c in all_commands() if action(c)[0] in ("validate", "slow")]


def test_every_validated_command_has_a_check():
    missing = {shlex.split(c.text)[2] for c in validated()} - set(CHECKS)
    assert not missing, f"no check for {missing}: add one to CHECKS"


@pytest.mark.parametrize("command", list(dict.fromkeys(validated())), ids=lambda c: f"{c.doc}:{c.line}")
def test_the_long_commands_parse_and_compose_as_written(command, tmp_path, monkeypatch):
    words = shlex.split(command.text)
    assert words[:2] == ["python", "-m"]
    monkeypatch.chdir(mirror(tmp_path / "root"))
    for name, value in doc_env(command.doc).items():
        monkeypatch.setenv(name, value)
    try:
        CHECKS[words[2]](words[3:])
    except SystemExit as err:  # argparse's refusal
        pytest.fail(f"{command}: its arguments do not parse (exit {err.code})")


@pytest.mark.parametrize("module, args", [
    ("overhang_framework.participants", ["cohort=paper_peple", "hydra.run.dir=runs/x"]),
    ("overhang_framework.participants", ["cohort=paper_people", "cohort.n_taks=2"]),
    ("overhang_framework.study", ["graded_budgets", "--out", "runs/g", "--fit", "+models.ipe.riskk=[0.5]"]),
    ("overhang_framework.study", ["graded_budgets", "--out", "runs/g", "--participants", "cohort.n_taks=2"]),
    ("overhang_framework.fit", ["runs/x/log.jsonl", "--out", "runs/f", "space=explanationz"]),
    ("overhang_framework.fit.recovery", ["--config-name", "recovery_explanations", "--out", "runs/e", "cachee=x"]),
    ("overhang_framework.experiment", ["studdy=graded_budgets"]),
    ("overhang_framework.experiment", ["pilot", "--out", "runs/p", "cohort=smal"]),
    ("overhang_framework.experiment.practice", ["practice.tolerence=0.02"]),
    ("overhang_framework.bench.pilot_recovery", ["--out", "runs/r", "--fit", "models.ipe.KK=20", "cohort=small"]),
    ("overhang_framework.behaviour.calibrate", ["fit", "t.csv", "--out", "o", "--proposal", "proposal_peple"]),
], ids=lambda v: v if isinstance(v, str) else " ".join(v)[:40])
def test_the_checks_refuse_a_misspelt_command(module, args, tmp_path, monkeypatch):
    """What the validation would catch in a doc: a misspelt key or config name is refused, in one line."""
    from overhang_framework.errors import OverhangError

    monkeypatch.chdir(mirror(tmp_path / "root"))
    monkeypatch.setenv("OVERHANG_ADMIN_TOKEN", "a-long-enough-admin-token")
    with pytest.raises(OverhangError):
        CHECKS[module](args)
