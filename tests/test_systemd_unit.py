"""The systemd unit: hardened, restarted only when a restart can help, and consistent with the airborne
profile and with the install steps in docs/companion.md (one binary, one profile, the cache read-only, the FDR
writable)."""

from __future__ import annotations

import dataclasses
import re
import shlex
import shutil
import subprocess
from pathlib import Path, PurePosixPath

import pytest

from gps_denied_onboard.cli import EXIT_CONFIG, EXIT_RESOURCE, build_parser
from gps_denied_onboard.config import load_config

ROOT = Path(__file__).resolve().parents[1]
UNIT_PATH = ROOT / "systemd" / "gdnav.service"
#: Where a unit's paths are hidden from the service by PrivateTmp=/ProtectHome=.
HIDDEN_ROOTS = ("/tmp", "/var/tmp", "/home", "/root", "/run/user")
_TRUE = {"yes", "true", "on", "1"}


def _parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """Section -> key -> every value in file order (keys such as ReadOnlyPaths= may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.endswith("\\"):
            raise ValueError(f"{UNIT_PATH.name}:{lineno}: continuation lines are not parsed here")
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        key, sep, value = line.partition("=")
        if current is None or not sep:
            raise ValueError(f"{UNIT_PATH.name}:{lineno}: not a directive inside a section: {raw!r}")
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


UNIT_TEXT = UNIT_PATH.read_text()
UNIT = _parse_unit(UNIT_TEXT)
PROFILE = load_config(ROOT / "config" / "airborne.yaml")


def _one(section: str, key: str) -> str:
    values = UNIT.get(section, {}).get(key, [])
    assert len(values) == 1, f"[{section}] {key}= must appear once, found {values}"
    return values[0]


def _words(section: str, key: str) -> list[str]:
    """A list-valued directive: every assignment, split on whitespace ('' resets the list, as in systemd)."""
    words: list[str] = []
    for value in UNIT.get(section, {}).get(key, []):
        words = [] if value == "" else [*words, *value.split()]
    return words


def _seconds(span: str) -> float:
    """A systemd time span such as `5`, `5s`, `500ms`, `2min` (bare numbers are seconds)."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*(ms|s|sec|min|m)?", span)
    assert m, f"unsupported time span {span!r}"
    scale = {"ms": 1e-3, "min": 60.0, "m": 60.0}.get(m.group(2) or "s", 1.0)
    return float(m.group(1)) * scale


def _exec(key: str) -> list[str]:
    """The argv of an Exec*= line; systemd's prefixes ('-', '+', '@', ...) are refused, not stripped."""
    argv = shlex.split(_one("Service", key))
    assert argv[0].startswith("/"), f"{key}= must name an absolute path: {argv[0]}"
    return argv


def _option(argv: list[str], name: str) -> str:
    assert argv.count(name) == 1, f"{name} must be given once: {argv}"
    return argv[argv.index(name) + 1]


def _paths(key: str) -> list[PurePosixPath]:
    """Paths of ReadOnlyPaths=/ReadWritePaths=, without the '-' (ignore if missing) and '+' prefixes."""
    return [PurePosixPath(w.lstrip("-+")) for w in _words("Service", key)]


def _writable() -> list[PurePosixPath]:
    state = [PurePosixPath("/var/lib") / d for d in _words("Service", "StateDirectory")]
    return state + _paths("ReadWritePaths")


def _under(path: str | None, roots: list[PurePosixPath]) -> bool:
    return path is not None and any(PurePosixPath(path).is_relative_to(r) for r in roots)


def _install_section() -> str:
    page = (ROOT / "docs" / "companion.md").read_text()
    assert "\n## Install on a companion computer\n" in page
    return page.split("\n## Install on a companion computer\n", 1)[1].split("\n## ", 1)[0]


def test_unit_every_directive_has_a_comment() -> None:
    """Each directive is preceded by a comment saying why it is there."""
    previous = ""
    for lineno, raw in enumerate(UNIT_TEXT.splitlines(), 1):
        line = raw.strip()
        if line and line[0] not in "#;[":
            assert previous.startswith("#"), f"{UNIT_PATH.name}:{lineno}: {line} has no comment above it"
        if line:
            previous = line


def test_unit_is_notify_with_a_watchdog_the_daemon_can_keep() -> None:
    """Type=notify (READY/WATCHDOG/STOPPING come from the daemon itself), and the watchdog spans several
    of the status task's pings in the airborne profile."""
    assert _one("Service", "Type") == "notify"
    assert _one("Service", "NotifyAccess") == "main"
    watchdog_s = _seconds(_one("Service", "WatchdogSec"))
    # daemon/service.py pings every min(1/status_hz, 1/named_value_hz, WatchdogSec/2).
    ping_s = min(1.0 / PROFILE.daemon.status_hz, 1.0 / PROFILE.mavlink.named_value_hz, watchdog_s / 2)
    assert watchdog_s >= 4 * ping_s, f"WatchdogSec={watchdog_s} s leaves no room for a late {ping_s} s ping"


def test_unit_does_not_restart_refusals() -> None:
    """Restart=on-failure, but never on exit 2 (configuration) or 3 (refused file or port)."""
    assert _one("Service", "Restart") == "on-failure"
    prevented = _words("Service", "RestartPreventExitStatus")
    assert {str(EXIT_CONFIG), str(EXIT_RESOURCE)} <= set(prevented), prevented
    assert (EXIT_CONFIG, EXIT_RESOURCE) == (2, 3)


def test_unit_restarts_a_daemon_ended_by_sighup() -> None:
    """systemd counts a death by SIGHUP as a clean stop (no restart under on-failure): the unit forces the
    restart for it, and the daemon ignores SIGHUP, SIGUSR1 and SIGUSR2 itself (daemon/signals.py; a death
    by SIGUSR1/2 is unclean, so on-failure restarts it anyway)."""
    from gps_denied_onboard.daemon.signals import IGNORED_SIGNALS

    assert "SIGHUP" in _words("Service", "RestartForceExitStatus")
    assert {s.name for s in IGNORED_SIGNALS} == {"SIGHUP", "SIGUSR1", "SIGUSR2"}


def test_unit_has_no_start_check_that_delays_a_restart_or_escapes_the_exit_codes() -> None:
    """No ExecStartPre=: `gdnav run` refuses what `gdnav config check` refuses with the same exit codes,
    which RestartPreventExitStatus= sees only from the main process, and a separate check spent 2-3.6 s of
    imports before every restart in flight, where ArduPilot declares no-fix 4 s after the last GPS_INPUT
    (issue 27). The start limit still ends a daemon that keeps failing soon after its start."""
    assert "ExecStartPre" not in UNIT["Service"]
    assert _seconds(_one("Service", "RestartSec")) <= 1.0
    burst = int(_one("Unit", "StartLimitBurst"))
    interval_s = _seconds(_one("Unit", "StartLimitIntervalSec"))
    assert burst >= 1 and burst * _seconds(_one("Service", "RestartSec")) < interval_s, (burst, interval_s)


def test_unit_runs_the_daemon_from_its_install_on_an_absolute_profile() -> None:
    """ExecStart is `gdnav run` with an absolute --config, from an install the sandbox does not hide, and
    with no prefix ('-' would ignore a refusal, '+' would run as root instead of the service user)."""
    run = _exec("ExecStart")
    assert PurePosixPath(run[0]).name == "gdnav" and run[1] == "run"
    assert PurePosixPath(_option(run, "--config")).is_absolute()
    assert not _under(run[0], [PurePosixPath(h) for h in HIDDEN_ROOTS])
    build_parser().parse_args(run[1:])


def test_unit_is_hardened() -> None:
    """A dedicated user with the device groups it needs, and the sandbox the README describes."""
    assert _one("Service", "User") == "gdnav"
    assert _one("Service", "Group") == "gdnav"
    assert {"dialout", "video"} <= set(_words("Service", "SupplementaryGroups"))
    for key in ("NoNewPrivileges", "PrivateTmp", "ProtectHome"):
        assert _one("Service", key).lower() in _TRUE, key
    assert _one("Service", "ProtectSystem") == "strict"


def test_unit_sandbox_fits_the_airborne_profile() -> None:
    """Under ProtectSystem=strict the FDR directory is writable, the cache and models are read-only, and
    no file the daemon reads is hidden by PrivateTmp=/ProtectHome=."""
    writable, read_only = _writable(), _paths("ReadOnlyPaths")
    assert _under(PROFILE.fdr.dir, writable), (PROFILE.fdr.dir, writable)
    assert _under(PROFILE.cache.dir, read_only), (PROFILE.cache.dir, read_only)
    assert not _under(PROFILE.cache.dir, writable)
    models = [
        getattr(PROFILE.matcher, f.name)
        for f in dataclasses.fields(PROFILE.matcher)
        if (f.name.endswith("_weights_path") or f.name == "model_dir")
        and getattr(PROFILE.matcher, f.name) is not None
    ]
    assert models, "the airborne profile names its model files"
    for path in models:
        assert _under(path, read_only) and not _under(path, writable), path
    hidden = [PurePosixPath(h) for h in HIDDEN_ROOTS]
    for path in (PROFILE.camera.calibration_file, PROFILE.cache.dir, PROFILE.fdr.dir, *models):
        assert path is not None and PurePosixPath(path).is_absolute(), path
        assert not _under(path, hidden), path


def test_readme_install_steps_match_the_unit() -> None:
    """docs/companion.md's install commands create what the unit runs and reads, and name its settings."""
    text = _install_section()
    run = _exec("ExecStart")
    binary, config = run[0], _option(run, "--config")
    venv = PurePosixPath(binary).parents[1]
    user, group = _one("Service", "User"), _one("Service", "Group")
    expected = [
        f"useradd --system --user-group --home-dir /nonexistent --no-create-home "
        f"--shell /usr/sbin/nologin {user}",
        f"python3 -m venv {venv}",
        f"{venv}/bin/pip install .",
        f"install -m 0644 config/airborne.yaml {config}",
        f"install -m 0644 nav_camera.yaml {PROFILE.camera.calibration_file}",
        f"install -o {user} -g {group} -m 0600 mavlink.key",
        f"{binary} cache build --source ortho.tif --out {PROFILE.cache.dir}",
        f"install -m 0644 systemd/gdnav.service /etc/systemd/system/{UNIT_PATH.name}",
        f"sudo -u {user} {binary} config check --config {config}",
        "systemctl enable --now gdnav",
        "journalctl -u gdnav",
        f"RestartPreventExitStatus={' '.join(_words('Service', 'RestartPreventExitStatus'))}",
        f"StartLimitBurst={_one('Unit', 'StartLimitBurst')}",
        f"StartLimitIntervalSec={_one('Unit', 'StartLimitIntervalSec')}",
        f"WatchdogSec={_one('Service', 'WatchdogSec')}",
        f"RestartSec={_one('Service', 'RestartSec')}",
    ]
    missing = [e for e in expected if e not in text]
    assert not missing, f"docs/companion.md install section lacks: {missing}"
    assert user == group, "docs/companion.md creates the user with --user-group"


def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    """`systemd-analyze verify` accepts the unit with no warning (the binary is stubbed: it checks that
    the executable exists)."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    binary = _exec("ExecStart")[0]
    stub = tmp_path / "gdnav"
    stub.write_text("#!/bin/sh\nexit 0\n")
    stub.chmod(0o755)
    unit = tmp_path / UNIT_PATH.name
    unit.write_text(UNIT_TEXT.replace(binary, str(stub)))
    proc = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60, check=False
    )
    ours = [ln for ln in (proc.stdout + proc.stderr).splitlines() if UNIT_PATH.name in ln]
    assert proc.returncode == 0 and not ours, proc.stdout + proc.stderr


#: The largest resident set measured for one daemon-like process (docs/benchmarks.md: DISK, classical and a
#: precomputed twin in one process, 2.6-2.9 GB); the unit's MemoryMax= must leave it a margin.
MEASURED_PEAK_RSS_BYTES = 2.9e9
#: `systemd-analyze security`'s exposure (0-10) at or below which it says "OK" or better.
SECURITY_OK_EXPOSURE = 4.9


def _bytes(size: str) -> float:
    """A systemd size such as `4G`, `512M` or a plain number of bytes (1024-based suffixes)."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([KMGT]?)", size)
    assert m, f"unsupported size {size!r}"
    return float(m.group(1)) * 1024.0 ** " KMGT".index(m.group(2) or " ")


def test_unit_filters_system_calls_and_socket_families() -> None:
    """A system-call allow list (@system-service, minus @privileged; a refused call fails with EPERM
    rather than killing the daemon in flight), native ABI only, and only the socket families it uses."""
    assert _words("Service", "SystemCallFilter") == ["@system-service", "~@privileged"]
    assert _one("Service", "SystemCallErrorNumber") == "EPERM"
    assert _one("Service", "SystemCallArchitectures") == "native"
    assert set(_words("Service", "RestrictAddressFamilies")) == {"AF_UNIX", "AF_INET", "AF_INET6"}


def test_unit_caps_memory_with_a_margin_over_the_measured_peak() -> None:
    """MemoryMax= is set, at least 25 % above the largest measured resident set."""
    assert _bytes(_one("Service", "MemoryMax")) >= 1.25 * MEASURED_PEAK_RSS_BYTES


def test_unit_protects_the_kernel_and_drops_every_capability() -> None:
    """Kernel tunables, modules, logs, cgroups and the host name are out of reach; no capability, no
    real-time class, no namespaces, no SUID files; files it creates are not world-readable."""
    for key in (
        "ProtectKernelTunables",
        "ProtectKernelModules",
        "ProtectKernelLogs",
        "ProtectControlGroups",
        "ProtectHostname",
        "PrivateMounts",
        "LockPersonality",
        "RestrictRealtime",
        "RestrictSUIDSGID",
        "RestrictNamespaces",
        "RemoveIPC",
    ):
        assert _one("Service", key).lower() in _TRUE, key
    assert _one("Service", "CapabilityBoundingSet") == ""
    assert _one("Service", "AmbientCapabilities") == ""
    assert _one("Service", "ProtectProc") == "invisible"
    assert _one("Service", "UMask") == "0027"


def test_unit_keeps_the_serial_link_and_the_camera_reachable() -> None:
    """No device allow-list is switched on, not even implicitly: ProtectClock= implies DeviceAllow=char-rtc,
    which would shut out /dev/ttyTHS1 and /dev/video0 (the airborne profile's); PrivateDevices= hides them
    and PrivateUsers= unmaps the groups that grant them."""
    assert PROFILE.mavlink.url.startswith("/dev/") and PROFILE.camera.source.startswith("v4l2:/dev/")
    for key in ("ProtectClock", "PrivateDevices", "PrivateUsers", "DeviceAllow", "DevicePolicy"):
        assert key not in UNIT["Service"], f"{key}= would cut the daemon off its devices"


def test_unit_gives_the_debug_log_a_writable_directory() -> None:
    """LogsDirectory= makes /var/log/gdnav writable under ProtectSystem=strict and sets LOGS_DIRECTORY,
    where a command's unexpected exception keeps its traceback (logging_setup.debug_log_path)."""
    assert _one("Service", "LogsDirectory") == "gdnav"


def test_unit_systemd_analyze_security_is_ok(tmp_path: Path) -> None:
    """`systemd-analyze security --offline=yes` rates the unit "OK" or better (it said 8.5 EXPOSED)."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    unit = tmp_path / UNIT_PATH.name
    unit.write_text(UNIT_TEXT)
    proc = subprocess.run(
        [analyze, "security", "--offline=yes", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d) (\w+)", proc.stdout)
    assert m, proc.stdout + proc.stderr
    assert float(m.group(1)) <= SECURITY_OK_EXPOSURE and m.group(2) in ("OK", "SAFE", "PERFECT"), m.group(0)


def test_the_real_autopilot_flights_restart_with_the_units_delay() -> None:
    """A restart flown on an external autopilot (``sitl.autopilot_flight``) leaves the gap the unit
    would: its RestartSec=."""
    from gps_denied_onboard.sitl.autopilot_flight import UNIT_RESTART_SEC_S

    assert _seconds(_one("Service", "RestartSec")) == UNIT_RESTART_SEC_S
