"""Deployment files: systemd units (systemd-analyze verify), udev rules, install and credentials."""

from __future__ import annotations

import json
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from racecav.deploy import credentials, install
from racecav.deploy.units import parse_unit, service_command
from tests.deploy_support import ensure_tool

ROOT = Path(__file__).resolve().parents[1]
SYSTEMD = ROOT / "deploy" / "systemd"


def systemd_analyze() -> str:
    """systemd-analyze, installed with the systemd package if missing (see ensure_tool)."""
    return ensure_tool("systemd-analyze", "systemd")


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """An install into a temporary root using this venv (no venv creation, no systemctl)."""
    ensure_tool("openssl", "openssl")
    root = tmp_path_factory.mktemp("root")
    plan = install.install(install.Layout(root=root, venv=sys.prefix), car="car0", tls=True, systemctl=False)
    return root, plan


def test_systemd_analyze_verify_every_unit(installed):
    root, _ = installed
    units = sorted((root / "etc/systemd/system").glob("racecav*"))
    assert [u.name for u in units] == sorted(f.name for f in install.unit_files())
    r = subprocess.run([systemd_analyze(), "verify", "--man=no", *map(str, units)], capture_output=True, text=True)
    ours = [ln for ln in (r.stdout + r.stderr).splitlines() if "racecav" in ln]
    assert r.returncode == 0 and not ours, r.stdout + r.stderr


def test_hardening_exposure_stays_low(installed):
    # systemd's own score of the sandbox (0 = locked down, 10 = exposed); ours are 1.4-1.6.
    root, _ = installed
    for name in install.SERVICES:
        unit = root / f"etc/systemd/system/racecav-{name}.service"
        r = subprocess.run([systemd_analyze(), "security", "--offline=yes", "--no-pager", "--threshold=20",
                            str(unit)], capture_output=True, text=True)
        level = re.search(r"Overall exposure level for \S+: ([0-9.]+)", r.stdout)
        assert r.returncode == 0 and level and float(level.group(1)) <= 2.0, r.stdout[-500:] + r.stderr


def test_systemd_analyze_catches_a_broken_unit(installed, tmp_path):
    # The check above can fail: a unit whose program is missing is an error, a typo a warning.
    root, _ = installed
    text = (root / "etc/systemd/system/racecav-sensor.service").read_text()
    bad = tmp_path / "racecav-sensor.service"
    bad.write_text(text.replace(sys.prefix, "/nonexistent").replace("Type=notify", "Typo=notify"))
    r = subprocess.run([systemd_analyze(), "verify", "--man=no", str(bad)], capture_output=True, text=True)
    assert r.returncode != 0 and "Typo" in r.stderr and "/nonexistent" in r.stderr


def test_units_share_one_common_block_and_declare_the_contract():
    def common(text: str) -> str:
        return text[text.index("# --- common"):text.index("# --- end of the common part ---")]

    services = {s: (SYSTEMD / f"racecav-{s}.service").read_text() for s in install.SERVICES}
    blocks = {common(t) for t in services.values()}
    assert len(blocks) == 1
    from racecav.cli import COMMANDS

    for name, text in services.items():
        unit = parse_unit(SYSTEMD / f"racecav-{name}.service")
        svc, u = unit["Service"], unit["Unit"]
        assert svc["Type"] == ["notify"] and float(svc["WatchdogSec"][0]) > 0
        assert svc["Restart"] == ["on-failure"] and u["StartLimitBurst"] and u["StartLimitIntervalSec"]
        assert svc["User"] == ["racecav"] and svc["EnvironmentFile"][-1] == "/etc/racecav/racecav.env"
        assert "RACECAV_CONFIG=/etc/racecav/racecav.toml" in svc["Environment"]
        argv = svc["ExecStart"][0].split()
        assert argv[0] == "/opt/racecav/venv/bin/racecav" and argv[1] == name and name in COMMANDS
        assert unit["Install"]["WantedBy"] == ["racecav.target"] and u["PartOf"] == ["racecav.target"]
        if name != "router":
            assert "racecav-router.service" in u["After"][0].split()
            assert svc["EnvironmentFile"][0] == f"/etc/racecav/credentials/{name}.env"
            assert svc["IPAddressDeny"] == ["any"] and svc["IPAddressAllow"] == ["localhost"]
    conflicts = {n: parse_unit(SYSTEMD / f"racecav-{n}.service")["Unit"].get("Conflicts", [""])[0]
                 for n in install.SERVICES}
    assert conflicts["sensor"] == "racecav-sim.service" and conflicts["sim"] == "racecav-sensor.service"
    assert conflicts["policy"] == "racecav-baseline.service" and conflicts["baseline"] == "racecav-policy.service"
    for serial, kind in (("sensor", "ttyUSB"), ("actuator", "ttyACM")):
        svc = parse_unit(SYSTEMD / f"racecav-{serial}.service")["Service"]
        assert svc["SupplementaryGroups"] == ["dialout"] and svc["DeviceAllow"] == [f"char-{kind} rw"]
        assert "PrivateDevices" not in svc  # a private /dev would hide a re-plugged device
    for other in ("router", "sim", "policy", "baseline"):
        assert parse_unit(SYSTEMD / f"racecav-{other}.service")["Service"]["PrivateDevices"] == ["yes"]


def test_udev_rules_name_the_devices_by_vendor_and_product():
    rules = [ln for ln in (ROOT / "deploy/udev/99-racecav.rules").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    parsed = {}
    for ln in rules:
        pairs = [p.strip() for p in ln.split(",")]
        kv = {}
        for p in pairs:
            m = re.fullmatch(r'([A-Z]+(?:\{\w+\})?)\s*(==|\+=|:=|=)\s*"([^"]*)"', p)
            assert m, f"not a udev key/value: {p!r}"
            kv[m.group(1)] = (m.group(2), m.group(3))
        parsed[kv["SYMLINK"][1]] = kv
    # hardware-protocols.md: RPLIDAR S2 behind a CP210x 10c4:ea60, VESC USB CDC 0483:5740
    for name, vid, pid in (("rplidar", "10c4", "ea60"), ("vesc", "0483", "5740")):
        assert parsed[name]["ATTRS{idVendor}"] == ("==", vid) and parsed[name]["ATTRS{idProduct}"] == ("==", pid)
    for kv in parsed.values():
        assert kv["SYMLINK"][0] == "+=" and kv["GROUP"] == ("=", "dialout") and kv["MODE"] == ("=", "0660")
        assert kv["ENV{ID_MM_DEVICE_IGNORE}"] == ("=", "1")


def test_install_dry_run_lists_everything_and_writes_nothing(tmp_path):
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "deploy", "install", "--dry-run", "--root", str(tmp_path),
                        "--venv", sys.prefix], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for f in install.unit_files():
        assert f"would write {tmp_path}/etc/systemd/system/{f.name}" in out
    for what in ("etc/udev/rules.d/99-racecav.rules", "etc/racecav/racecav.toml", "etc/racecav/racecav.env",
                 "etc/racecav/zenoh/passwords.txt", "etc/racecav/zenoh/router.json5",
                 "etc/racecav/credentials/policy.env", "etc/racecav/tls/ca.pem"):
        assert str(tmp_path / what) in out
    assert list(tmp_path.iterdir()) == []


def test_install_writes_files_with_safe_modes_and_keeps_secrets_on_rerun(installed):
    root, plan = installed
    etc = root / "etc/racecav"
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    assert mode(etc / "zenoh/passwords.txt") == 0o640 and mode(etc / "tls/router.key") == 0o640
    for acct in credentials.ACCOUNTS:
        assert mode(etc / "credentials" / f"{acct}.env") == 0o600
    assert mode(etc / "tls/ca.key") == 0o600 and mode(etc / "tls/monitor.key") == 0o600
    users = dict(ln.split(":", 1) for ln in (etc / "zenoh/passwords.txt").read_text().splitlines())
    assert sorted(users) == sorted(credentials.ACCOUNTS) and len(set(users.values())) == len(users)
    # Units point at this install: the venv and the root's /etc/racecav.
    argv, env = service_command(root / "etc/systemd/system/racecav-policy.service")
    assert argv == [f"{sys.prefix}/bin/racecav", "policy"]
    assert env["RACECAV_CONFIG"] == str(etc / "racecav.toml") and env["RACECAV_BUS__USER"] == "policy"
    before = (etc / "zenoh/passwords.txt").read_text(), (etc / "tls/ca.pem").read_text()
    (etc / "racecav.toml").write_text((etc / "racecav.toml").read_text() + "# edited by the user\n")
    install.install(install.Layout(root=root, venv=sys.prefix), tls=True, systemctl=False)
    assert ((etc / "zenoh/passwords.txt").read_text(), (etc / "tls/ca.pem").read_text()) == before
    assert (etc / "racecav.toml").read_text().endswith("# edited by the user\n")


@pytest.mark.parametrize("tls", [True, False])
def test_router_config_loads_in_zenoh_and_lists_every_account(tmp_path, tls):
    import zenoh

    credentials.make_credentials(tmp_path, "car7", tls=tls, group=None)
    conf = zenoh.Config.from_file(str(tmp_path / "zenoh/router.json5"))
    assert json.loads(conf.get_json("listen/endpoints")) == credentials.router_listen(tls)
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert all(r["permission"] == "allow" for r in acl["rules"])  # a deny would beat any allow
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert sorted(subjects["accounts"]["usernames"]) == sorted(credentials.ACCOUNTS)
    named = {u for s in acl["subjects"] for u in s["usernames"] or []}
    assert named == set(credentials.ACCOUNTS)
    # Only the remote accounts match without the loopback interface.
    off_car = {u for s in acl["subjects"] if s["id"] != "accounts" and not s["interfaces"] for u in s["usernames"]}
    assert off_car == set(credentials.REMOTE_ACCOUNTS)
    keys = {k for r in acl["rules"] for k in r["key_exprs"]}
    assert all(k.startswith("racecav/car7/") for k in keys)
    tls_conf = json.loads(conf.get_json("transport/link/tls"))
    if tls:  # clients on tls/ endpoints must show a certificate of the local CA
        assert tls_conf["listen_certificate"] == str(tmp_path / "tls/router.pem") and tls_conf["enable_mtls"]
    else:
        assert not tls_conf.get("listen_certificate")


def test_broken_password_file_names_the_line(tmp_path):
    (tmp_path / "zenoh").mkdir()
    (tmp_path / "zenoh/passwords.txt").write_text("policy:abc\nno-colon-here\n")
    with pytest.raises(ValueError, match="passwords.txt:2"):
        credentials.make_credentials(tmp_path, "car0", tls=False, group=None)
