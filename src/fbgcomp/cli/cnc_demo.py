"""``fbgcomp cnc-demo``: the compensator moving a (simulated) LinuxCNC machine's tool.

:class:`LinuxCncMachine` starts the example machine of ``examples/linuxcnc`` headless - as an
unprivileged user when run as root, because ``linuxcnc`` refuses to run as root - in a private
copy of the configuration, talks to its headless display (``fbgcomp.cnc.fbgcomp_display``) and
stops everything it started: first through LinuxCNC's own shutdown path (the display exits, the
``linuxcnc`` script unloads HAL and stops rtapi_app, task and io), then, if anything is left,
``halrun -U`` and the process group. The tests use the same class.

:func:`run_demo` homes the machine, starts ``fbgcomp serve --cnc linuxcnc`` on a thermal
campaign replayed through the simulated interrogator at an accelerated speed, runs a short
G-code program and prints commanded and compensated positions.

The models and the campaign writer are imported inside :func:`run_demo`'s helpers so that
``fbgcomp --help``, which imports this module to mount ``cnc-demo``, starts fast.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import typer

from fbgcomp.errors import InputError

CNC_USER = "fbgcomp-cnc"
LOCK_PATH = "/tmp/fbgcomp-linuxcnc.lock"  # HAL shared memory is machine-wide: one instance
CONFIG_FILES = ("fbgcomp-mill.ini", "fbgcomp-mill.hal", "tool.tbl", "demo.ngc")
SCRIPTS = ("fbgcomp_hal.py", "fbgcomp_display.py")


class CncError(RuntimeError):
    """LinuxCNC did not start, answer or do what it was asked (the message says which)."""


def example_dir() -> Path:
    """examples/linuxcnc of the source tree this package was installed from."""
    return Path(__file__).resolve().parents[3] / "examples" / "linuxcnc"


def ensure_user(name: str = CNC_USER) -> pwd.struct_passwd | None:
    """The unprivileged account LinuxCNC runs as when we are root (created if missing);
    None when we are not root (LinuxCNC then runs as ourselves)."""
    if os.geteuid() != 0:
        return None
    try:
        return pwd.getpwnam(name)
    except KeyError:
        subprocess.run(
            [
                "useradd",
                "--system",
                "--user-group",
                "--no-create-home",
                "--home-dir",
                "/nonexistent",
                "--shell",
                "/usr/sbin/nologin",
                name,
            ],
            check=True,
            capture_output=True,
            timeout=30,
        )
        return pwd.getpwnam(name)


def _set_ini(text: str, section: str, values: dict) -> str:
    """Replace ``KEY = value`` lines of one INI section (LinuxCNC INI: no inline comments)."""
    out, current, done = [], None, set()
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("[") and s.endswith("]"):
            if current == section:
                out.extend(f"{k} = {v}" for k, v in values.items() if k not in done)
            current = s[1:-1]
        elif current == section and "=" in s and not s.startswith("#"):
            key = s.split("=", 1)[0].strip()
            if key in values:
                line = f"{key} = {values[key]}"
                done.add(key)
        out.append(line)
    if current == section:
        out.extend(f"{k} = {v}" for k, v in values.items() if k not in done)
    return "\n".join(out) + "\n"


def free_udp_port() -> int:
    """A UDP port on the loopback interface that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LinuxCncMachine:
    """The simulated machine, headless. Use as a context manager; every wait is bounded."""

    def __init__(
        self,
        config_dir: str | Path | None = None,
        *,
        fbgcomp: dict | None = None,
        user: str = CNC_USER,
        start_timeout_s: float = 60.0,
    ):
        self.config_dir = Path(config_dir) if config_dir else example_dir()
        self.port = free_udp_port()
        self.fbgcomp = {"LISTEN": f"udp://127.0.0.1:{self.port}", **(fbgcomp or {})}
        self.user = user
        self.start_timeout_s = start_timeout_s
        self.proc: subprocess.Popen | None = None
        self.run_dir: Path | None = None
        self._lock_fd: int | None = None
        self._sock: socket.socket | None = None
        self._file: io.BufferedIOBase | None = None

    @property
    def address(self) -> str:
        """The local channel to give ``fbgcomp serve --cnc-address``."""
        return self.fbgcomp["LISTEN"]

    # -- start / stop
    def _lock(self, timeout_s: float) -> None:
        fd = os.open(LOCK_PATH, os.O_RDWR | os.O_CREAT, 0o666)
        end = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > end:
                    os.close(fd)
                    raise CncError(f"another LinuxCNC instance holds {LOCK_PATH}") from None
                time.sleep(0.2)
        self._lock_fd = fd

    def _prepare(self, account) -> Path:
        missing = [f for f in CONFIG_FILES if not (self.config_dir / f).is_file()]
        if missing:
            raise CncError(f"{self.config_dir}: missing {', '.join(missing)}")
        run = Path(tempfile.mkdtemp(prefix="fbgcomp-cnc-"))
        for f in CONFIG_FILES:
            shutil.copyfile(self.config_dir / f, run / f)
        pkg = Path(__file__).resolve().parents[1] / "cnc"
        for f in SCRIPTS:
            shutil.copyfile(pkg / f, run / f)
            os.chmod(run / f, 0o755)
        ini = run / CONFIG_FILES[0]
        ini.write_text(_set_ini(ini.read_text(), "FBGCOMP", self.fbgcomp))
        os.chmod(run, 0o755)
        if account is not None:
            for p in [run, *run.iterdir()]:
                os.chown(p, account.pw_uid, account.pw_gid)
        return run

    def start(self) -> LinuxCncMachine:
        """Start LinuxCNC headless on a private copy of the configuration and connect to its
        display; on any failure everything started so far is stopped."""
        linuxcnc = shutil.which("linuxcnc")
        if linuxcnc is None:
            raise CncError("linuxcnc not found (apt-get install linuxcnc-uspace)")
        self._lock(self.start_timeout_s)
        try:
            account = ensure_user(self.user)
            self.run_dir = self._prepare(account)
            cmd = [linuxcnc, "-r", str(self.run_dir / CONFIG_FILES[0])]
            if account is not None:
                cmd = [
                    "runuser",
                    "-u",
                    account.pw_name,
                    "--",
                    "env",
                    f"HOME={self.run_dir}",
                    f"USER={account.pw_name}",
                    *cmd,
                ]
            env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
            # the child keeps its own copy of the log's descriptor
            with open(self.run_dir / "linuxcnc.log", "wb") as log:
                self.proc = subprocess.Popen(
                    cmd,
                    cwd=self.run_dir,
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    env=env,
                    start_new_session=True,
                )
            self._connect()
        except BaseException:
            self.stop()
            raise
        return self

    def _connect(self) -> None:
        assert self.run_dir is not None and self.proc is not None  # start() set them
        path = self.run_dir / "display.sock"
        end = time.monotonic() + self.start_timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise CncError(f"linuxcnc exited ({self.proc.returncode}):\n{self.log_tail()}")
            if path.exists():
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                try:
                    s.connect(str(path))
                except OSError:
                    s.close()
                else:
                    self._sock, self._file = s, s.makefile("rwb")
                    return
            time.sleep(0.1)
        raise CncError(f"the display did not come up in {self.start_timeout_s} s:\n{self.log_tail()}")

    def log_tail(self, n: int = 30) -> str:
        """The last ``n`` lines of LinuxCNC's log ("" when there is none)."""
        if self.run_dir is None:
            return ""
        try:
            lines = (self.run_dir / "linuxcnc.log").read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def _session_pids(self) -> list[int]:
        """Processes still in the session the machine was started in."""
        if self.proc is None:
            return []
        pids = []
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                if os.getsid(int(d.name)) == self.proc.pid:
                    pids.append(int(d.name))
            except (ProcessLookupError, PermissionError):
                pass
        return pids

    def stop(self, timeout_s: float = 30.0) -> None:
        """LinuxCNC's own shutdown first; whatever is left is killed. Safe to call twice."""
        try:
            if self._file is not None and self.proc is not None and self.proc.poll() is None:
                with contextlib.suppress(OSError, CncError, ValueError):
                    self.call("quit", timeout_s=5.0)
            if self._sock is not None:
                self._sock.close()
                self._sock = self._file = None
            if self.proc is not None:
                try:
                    self.proc.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    self._force_stop()
                left = self._session_pids()
                if left:
                    self._force_stop()
        finally:
            if self.run_dir is not None:
                shutil.rmtree(self.run_dir, ignore_errors=True)
                self.run_dir = None
            if self._lock_fd is not None:
                os.close(self._lock_fd)
                self._lock_fd = None

    def _force_stop(self) -> None:
        halrun = shutil.which("halrun")
        if halrun and self.run_dir is not None:
            cmd = [halrun, "-U"]
            if os.geteuid() == 0:
                cmd = ["runuser", "-u", self.user, "--", *cmd]
            with contextlib.suppress(subprocess.TimeoutExpired, OSError):
                subprocess.run(cmd, timeout=15, capture_output=True, cwd=self.run_dir)
        for sig in (signal.SIGTERM, signal.SIGKILL):
            pids = self._session_pids()
            if not pids:
                break
            for pid in pids:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, sig)
            end = time.monotonic() + 3.0
            while time.monotonic() < end and self._session_pids():
                time.sleep(0.1)
        assert self.proc is not None  # stop() calls this only for a started process
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(5.0)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- the display's protocol
    def call(self, cmd: str, timeout_s: float = 30.0, **kw) -> dict:
        """Send one command to the headless display and return its answer (CncError if not ok)."""
        if self._file is None or self._sock is None:  # both set by _connect, cleared by stop
            raise CncError("machine not started")
        self._sock.settimeout(timeout_s + 5.0)
        self._file.write((json.dumps({"cmd": cmd, "timeout_s": timeout_s, **kw}) + "\n").encode())
        self._file.flush()
        line = self._file.readline()
        if not line:
            raise CncError(f"the display closed the connection:\n{self.log_tail()}")
        ans = json.loads(line)
        if not ans.pop("ok", False):
            raise CncError(f"{cmd}: {ans.get('error')}")
        return ans

    def status(self, pins=None) -> dict:
        """The machine's status, with the values of ``pins`` when given."""
        return self.call("status", pins=pins)

    def getp(self, *pins) -> dict:
        """Values of HAL pins by name."""
        return self.call("getp", pins=list(pins))["values"]

    def setp(self, pin: str, value) -> None:
        """Set a HAL pin."""
        self.call("setp", pin=pin, value=value)


# -- the demo ------------------------------------------------------------------------------


def _demo_inputs(work: Path, model_path: Path | None, campaign_dir: Path | None, echo) -> tuple[Path, Path]:
    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.io.campaign import write_campaign
    from fbgcomp.models.mra import MRAModel

    if model_path is None:
        echo("fitting a model on a synthetic 2 h thermal campaign ...")
        train, _ = linear_truth_campaign("cnc-train", seed=11, duration_s=2 * 3600)
        model = MRAModel(features="eq13", zero_window_s=1.0, fallbacks="loo").fit(train)
        model_path = Path(model.save(work / "model.json"))
    if campaign_dir is None:
        # a different thermal history replayed through the simulated interrogator; the
        # signals move from the first sample (a resting replay would look like stuck gratings)
        replay, _ = linear_truth_campaign("cnc-replay", seed=12, duration_s=2 * 3600, settle_s=0.0)
        campaign_dir = Path(write_campaign(replay, work / "replay"))
    return model_path, campaign_dir


def _row(r, pins):
    t, cmd, act, vals = r
    v = dict(zip(pins, vals))
    corr = [v[f"fbgcomp.{a}.offset-um"] for a in "xyz"]
    eo = [v[f"axis.{a}.eoffset"] for a in "xyz"]
    return t, cmd, act, corr, eo


def run_demo(
    model_path: Path | None = None,
    campaign_dir: Path | None = None,
    speed: float = 300.0,
    program: Path | None = None,
    config_dir: Path | None = None,
    echo=print,
) -> dict:
    """Home the machine, compensate during a program run, print positions; stop everything."""
    pins = [f"fbgcomp.{a}.offset-um" for a in "xyz"] + [f"axis.{a}.eoffset" for a in "xyz"]
    work = Path(tempfile.mkdtemp(prefix="fbgcomp-cnc-demo-"))
    serve = None
    try:
        model_path, campaign_dir = _demo_inputs(work, model_path, campaign_dir, echo)
        with LinuxCncMachine(config_dir) as m:
            echo(f"LinuxCNC started (run folder {m.run_dir}); machine on, homing ...")
            m.call("machine_on")
            m.call("home")
            serve = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "fbgcomp",
                    "serve",
                    "--model",
                    str(model_path),
                    "--source",
                    f"sim://{campaign_dir}?rate=200&speed={speed:g}",
                    "--opcua",
                    "off",
                    "--cnc",
                    "linuxcnc",
                    "--cnc-address",
                    m.address,
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
            )
            echo(
                f"fbgcomp serve --cnc linuxcnc --cnc-address {m.address} "
                f"(campaign replayed at {speed:g}x) ..."
            )
            m.call("wait_pin", pin="fbgcomp.active", value=1, tol=0, timeout_s=30.0)
            prog = program or (m.run_dir / "demo.ngc")
            if program is not None:
                shutil.copyfile(program, m.run_dir / "program.ngc")
                os.chmod(m.run_dir / "program.ngc", 0o644)
                prog = m.run_dir / "program.ngc"
            m.call("program", path=str(prog), wait=False)
            # sample while the program runs, in bounded slices
            rows = []
            end = time.monotonic() + 120.0
            while time.monotonic() < end:
                tr = m.call("trace", pins=pins, duration_s=0.5, interval_s=0.05)
                rows.extend(tr["rows"])
                st = m.status()
                if st["interp_idle"]:
                    break
            final = m.status(pins)
            echo("")
            echo(
                "   t_s | commanded (program) X Y Z, mm | correction X Y Z, µm  | "
                "compensated (actual) X Y Z, mm"
            )
            t0 = rows[0][0] if rows else time.time()
            step = max(1, len(rows) // 30)
            for r in rows[::step]:
                t, pos, act, corr, eo = _row(r, pins)
                # LinuxCNC's commanded position includes the external offset: take it out
                cmd = [p - e for p, e in zip(pos, eo)]
                echo(
                    f"{t - t0:6.2f} | {cmd[0]:9.4f} {cmd[1]:9.4f} {cmd[2]:9.4f}    | "
                    f"{corr[0]:+6.2f} {corr[1]:+6.2f} {corr[2]:+6.2f} | "
                    f"{act[0]:10.5f} {act[1]:10.5f} {act[2]:10.5f}"
                )
            p = final["pins"]
            offs = [p[f"axis.{a}.eoffset"] for a in "xyz"]
            nominal = [round(q - o, 5) for q, o in zip(final["position"], offs)]
            echo(
                f"\nend of program: commanded {nominal} mm + external offset "
                f"{[round(o * 1000, 2) for o in offs]} µm = actual "
                f"{[round(a, 5) for a in final['actual']]} mm"
            )
            serve.send_signal(signal.SIGINT)
            try:
                serve.wait(20)
            except subprocess.TimeoutExpired:
                serve.kill()
            serve = None
            m.call("wait_pin", pin="motion.eoffset-active", value=0, tol=0, timeout_s=30.0)
            echo("compensator stopped: the offsets ramped back to zero; stopping LinuxCNC")
            return {"rows": rows, "pins": pins, "final": final}
    finally:
        if serve is not None and serve.poll() is None:
            serve.kill()
            serve.wait(10)
        shutil.rmtree(work, ignore_errors=True)


def cnc_demo(
    model: Path | None = typer.Option(
        None, "--model", help="Model file; default: fitted on a synthetic thermal campaign."
    ),
    campaign: Path | None = typer.Option(
        None, "--campaign", help="Campaign folder to replay; default: a synthetic 2 h thermal campaign."
    ),
    speed: float = typer.Option(300.0, "--speed", help="Campaign seconds per real second."),
    program: Path | None = typer.Option(
        None, "--program", help="G-code file to run (default examples/linuxcnc/demo.ngc)."
    ),
    config_dir: Path | None = typer.Option(
        None, "--config-dir", help="LinuxCNC configuration folder (default examples/linuxcnc)."
    ),
):
    """Run the compensator against a simulated, headless LinuxCNC mill (docs/linuxcnc.md)."""
    try:
        run_demo(model, campaign, speed, program, config_dir, echo=typer.echo)
    except CncError as exc:
        raise InputError(str(exc), column="cnc-demo") from exc
