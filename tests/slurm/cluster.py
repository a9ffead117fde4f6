"""A throw-away single-node Slurm cluster for tests, from Debian's ``slurmctld``, ``slurmd`` and ``munge``.

Everything lives in one fresh directory under ``/tmp`` (short, so that the
munge socket path stays under the 108-byte limit of a Unix socket): the munge
key and socket, ``slurm.conf`` naming this host with its CPUs and memory as
``slurmd -C`` reports them, the daemons' state, spool, pid and log files. The
ports are free ones picked at start-up, the cluster name is unique, and no
system file or service is touched, so several clusters (other test runs on the
same machine) can run side by side. The daemons run in the foreground as
children of the test process and are stopped, and the directory removed, on
teardown, whatever happened in between; should the test process itself be
killed, the daemons get SIGTERM from the kernel (``PR_SET_PDEATHSIG``). Every wait has a timeout; a failure
names what did not come up and shows the end of its log.

Commands that talk to the cluster (``sbatch``, ``sinfo``, submitit) need the
environment of :attr:`SlurmCluster.env` (``SLURM_CONF`` points at its config).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import uuid
from pathlib import Path
from typing import Optional

DAEMONS = ("munged", "mungekey", "slurmctld", "slurmd", "sinfo", "sbatch", "squeue")
SBIN = ("/usr/sbin", "/sbin", "/usr/bin", "/bin")


class SlurmUnavailable(RuntimeError):
    """Slurm cannot run here; the message says why (missing packages, not root)."""


class SlurmStartError(RuntimeError):
    """A daemon did not come up; the message names it and shows the end of its log."""


def which(name: str) -> Optional[str]:
    path = os.pathsep.join([os.environ.get("PATH", ""), *SBIN])
    return shutil.which(name, path=path)


def missing_programs() -> list[str]:
    return [name for name in DAEMONS if which(name) is None]


def unavailable_reason() -> Optional[str]:
    """Why a cluster cannot be started here, or None."""
    missing = missing_programs()
    if missing:
        return (f"Slurm/munge programs not found: {', '.join(missing)} "
                "(apt-get install slurmctld slurmd munge, as .ci/run does)")
    if os.geteuid() != 0:
        return "starting slurmd needs root (it runs the jobs as their submitting user)"
    return None


def _die_with_parent() -> None:
    """In the daemon's child process: get SIGTERM when the test process dies, even by SIGKILL (Linux)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tail(path: Path, lines: int = 15) -> str:
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return f"({path.name}: no log)"
    return f"--- end of {path.name} ---\n" + "\n".join(text[-lines:])


class SlurmCluster:
    """Start with :meth:`start`, stop with :meth:`stop` (safe to call whatever state start left)."""

    def __init__(self, timeout: float = 60.0):
        self.timeout = timeout
        self.dir = Path(tempfile.mkdtemp(prefix="ovh-slurm-", dir="/tmp"))
        self.name = "ovh" + uuid.uuid4().hex[:8]
        self.conf = self.dir / "slurm.conf"
        self.socket = self.dir / "munge.sock"
        self.procs: dict[str, subprocess.Popen] = {}
        self.env = dict(os.environ, SLURM_CONF=str(self.conf),
                        PATH=os.pathsep.join([os.environ.get("PATH", ""), *SBIN]))
        self.env.pop("SLURM_JOB_ID", None)  # not inside an outer allocation
        self.node = ""

    # ---- start-up -------------------------------------------------------------------------
    def start(self) -> "SlurmCluster":
        reason = unavailable_reason()
        if reason:
            raise SlurmUnavailable(reason)
        try:
            self._start_munge()
            self._write_conf()
            self._spawn("slurmctld", [which("slurmctld"), "-D", "-c", "-f", str(self.conf)])
            self._spawn("slurmd", [which("slurmd"), "-D", "-f", str(self.conf), "-N", self.node])
            self._wait_idle()
        except BaseException:
            self.stop()
            raise
        return self

    def _start_munge(self) -> None:
        key = self.dir / "munge.key"
        subprocess.run([which("mungekey"), "--create", f"--keyfile={key}"], check=True,
                       capture_output=True, timeout=30)
        key.chmod(0o600)
        log = self.dir / "munged.log"
        self._spawn("munged", [which("munged"), "-F", "-f", f"--socket={self.socket}", f"--key-file={key}",
                               f"--log-file={log}", f"--pid-file={self.dir / 'munged.pid'}",
                               f"--seed-file={self.dir / 'munged.seed'}"], log=log)
        self._wait("munged", self.socket.exists, log)

    def _write_conf(self) -> None:
        out = subprocess.run([which("slurmd"), "-C"], capture_output=True, text=True, timeout=30,
                             check=True).stdout
        node_line = next(line for line in out.splitlines() if line.startswith("NodeName="))
        fields = dict(item.split("=", 1) for item in node_line.split())
        self.node = fields["NodeName"]
        # leave memory headroom so that the node is not drained for having less than it claims
        fields["RealMemory"] = str(max(256, int(int(fields.get("RealMemory", "1024")) * 0.9)))
        node = " ".join(f"{k}={v}" for k, v in fields.items())
        for sub in ("state", "spool"):
            (self.dir / sub).mkdir()
        d = self.dir
        self.conf.write_text(f"""\
ClusterName={self.name}
SlurmctldHost={self.node}(127.0.0.1)
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={self.socket}
StateSaveLocation={d}/state
SlurmdSpoolDir={d}/spool
SlurmctldPidFile={d}/slurmctld.pid
SlurmdPidFile={d}/slurmd.pid
SlurmctldLogFile={d}/slurmctld.log
SlurmdLogFile={d}/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
InactiveLimit=0
KillWait=5
MinJobAge=300
{node} NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=debug Nodes={self.node} Default=YES MaxTime=INFINITE State=UP
""")

    def _spawn(self, name: str, argv: list, log: Optional[Path] = None) -> None:
        out = open(self.dir / f"{name}.out", "wb")
        self.procs[name] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            env=self.env, cwd=self.dir, start_new_session=True,
                                            preexec_fn=_die_with_parent)
        out.close()

    def _logs(self, name: str) -> str:
        return "\n".join(_tail(p) for p in (self.dir / f"{name}.out", self.dir / f"{name}.log") if p.exists())

    def _wait(self, name: str, ready, log: Optional[Path] = None) -> None:
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            proc = self.procs.get(name)
            if proc is not None and proc.poll() is not None:
                raise SlurmStartError(f"{name} exited with status {proc.returncode}\n{self._logs(name)}")
            if ready():
                return
            time.sleep(0.25)
        raise SlurmStartError(f"{name} not ready after {self.timeout:.0f} s\n{self._logs(name)}")

    def sinfo_state(self) -> str:
        try:
            proc = subprocess.run(["sinfo", "-h", "-N", "-n", self.node, "-o", "%T"], capture_output=True,
                                  text=True, env=self.env, timeout=10)
        except subprocess.TimeoutExpired:
            return ""
        return proc.stdout.strip() if proc.returncode == 0 else ""

    def _wait_idle(self) -> None:
        try:
            self._wait("slurmd", lambda: self.sinfo_state() == "idle")
        except SlurmStartError as err:
            raise SlurmStartError(f"node {self.node} is not idle (sinfo: {self.sinfo_state() or 'no answer'}); "
                                  f"{err}\n{self._logs('slurmctld')}") from None

    # ---- teardown -------------------------------------------------------------------------
    def stop(self) -> None:
        """Cancel the cluster's jobs, stop its daemons (TERM, then KILL), remove its directory."""
        if "slurmctld" in self.procs and self.procs["slurmctld"].poll() is None:
            try:
                subprocess.run(["scancel", "--full", "--quiet", f"--clusters={self.name}", "-u", "root"],
                               env=self.env, capture_output=True, timeout=10)
            except (OSError, subprocess.SubprocessError):
                pass
        for name in ("slurmd", "slurmctld", "munged"):
            proc = self.procs.pop(name, None)
            if proc is None:
                continue
            for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
                if proc.poll() is not None:
                    break
                try:
                    os.killpg(proc.pid, sig)  # its own session: the daemon and anything it forked
                except ProcessLookupError:
                    break
                try:
                    proc.wait(timeout=wait)
                except subprocess.TimeoutExpired:
                    pass
        shutil.rmtree(self.dir, ignore_errors=True)
