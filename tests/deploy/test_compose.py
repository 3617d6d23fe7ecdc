"""The compose file, checked without a Docker engine: every service command names a real module, every
profile is complete, required secrets are required, and the Dockerfile installs what Open3D needs. The
environment compose gives each service, interpolated as compose does, is read by that service's real settings
class: the header's drone command gets a RealSense camera, a serial bridge that publishes tf, and every
variable that compose or docs/*.md names is a real setting (or one of compose's own, used where it says)."""

from __future__ import annotations

import importlib.util
import os
import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]

PROFILES = {
    "ground": {"zenoh-ground", "gateway", "reasoner", "recorder"},
    "drone": {"zenoh-drone", "camera", "perception", "executor", "autopilot_bridge"},
    "sim": {"sim"},
    "px4-sitl": {"px4-sitl"},
}


def test_every_python_service_runs_a_real_module():
    for name, svc in SERVICES.items():
        if svc.get("image", "").startswith(("eclipse/zenoh", "px4io/")):
            continue
        cmd = svc["command"]
        if cmd[:2] == ["aermani.cli", "router"]:  # a secure router from shared/routers/
            assert name.startswith("zenoh-"), name
            continue
        assert len(cmd) == 1 and cmd[0].startswith("services."), (name, cmd)
        module = cmd[0]
        assert importlib.util.find_spec(module) is not None, f"{name}: no module {module}"
        assert importlib.util.find_spec(f"{module}.__main__") is not None, f"{name}: {module} has no __main__"


def test_profiles_are_complete():
    for profile, expected in PROFILES.items():
        members = {n for n, s in SERVICES.items() if profile in s.get("profiles", [])}
        assert members == expected, (profile, members)
    assert all(s.get("profiles") for s in SERVICES.values()), "every service belongs to a profile"


def test_services_connect_to_a_router_in_their_profile():
    """Services share their router's network namespace and reach it on loopback: no plain Zenoh link leaves
    the host (the routers' only outside listener is mutual TLS)."""
    for name, svc in SERVICES.items():
        env = svc.get("environment", {})
        endpoint = env.get("AERMANI_ZENOH_CONNECT")
        if endpoint is None:
            continue
        assert endpoint == "tcp/127.0.0.1:7447", (name, endpoint)
        router = svc["network_mode"].removeprefix("service:")
        assert router in SERVICES and router.startswith("zenoh-"), (name, svc["network_mode"])
        profiles = set(svc["profiles"])
        router_profiles = set(SERVICES[router]["profiles"])
        # A service either shares its router's profile or is meant to run beside it (sim rides on drone).
        assert profiles & router_profiles or (profiles == {"sim"} and "drone" in router_profiles), name


def test_routers_run_the_secure_templates():
    for name in ("zenoh-ground", "zenoh-drone"):
        cmd = SERVICES[name]["command"]
        role = cmd[cmd.index("--role") + 1]
        assert (ROOT / "shared" / "routers" / f"{role}.json5").is_file()
        assert any(v.endswith(":/certs:ro") for v in SERVICES[name]["volumes"])
        assert "--rest-http-port" not in cmd
    ground_ports = SERVICES["zenoh-ground"]["ports"]
    # Only the TLS listener (container port 7448; its host port is configurable) leaves the namespace.
    assert "${AERMANI_ROUTER_PUBLISH:-127.0.0.1:7448}:7448" in ground_ports
    assert not any(p.split(":")[-1].startswith("7447") for p in ground_ports)
    assert "ports" not in SERVICES["zenoh-drone"] or all("7447" not in p for p in SERVICES["zenoh-drone"]["ports"])
    # The bridge's MAVLink port reaches the host's loopback only (the bridge locks onto the first autopilot).
    assert SERVICES["zenoh-drone"]["ports"] == ["${AERMANI_MAVLINK_PUBLISH:-127.0.0.1:14540}:14540/udp"]


def test_restart_policies_and_healthchecks():
    for name, svc in SERVICES.items():
        assert svc.get("restart") == "unless-stopped", name
    assert "healthcheck" in SERVICES["zenoh-ground"] and "healthcheck" in SERVICES["gateway"]
    for name, svc in SERVICES.items():
        for dep, cond in (svc.get("depends_on") or {}).items():
            assert dep in SERVICES and "healthcheck" in SERVICES[dep], (name, dep, cond)


def test_secrets_are_required_not_defaulted():
    text = (ROOT / "docker-compose.yml").read_text()
    assert re.search(r"AERMANI_GATEWAY_TOKEN: \$\{AERMANI_GATEWAY_TOKEN:\?", text)
    assert "OPENAI_API_KEY: ${OPENAI_API_KEY:-}" in text  # passed through, never written down


def test_drone_router_links_to_ground_router():
    cmd = SERVICES["zenoh-drone"]["command"]
    link = cmd[cmd.index("--connect") + 1]
    assert "AERMANI_GROUND_ROUTER" in link and "tls/" in link


def test_dockerfile_installs_open3d_runtime_libraries():
    text = (ROOT / "Dockerfile").read_text()
    for lib in ("libusb-1.0-0", "libgl1", "libegl1", "libgomp1"):
        assert lib in text


def test_environment_variables_name_real_settings():
    """A misspelt AERMANI_<SERVICE>_* variable would be silently ignored by pydantic-settings."""
    import importlib

    classes = {}
    for name in ("sim", "camera", "autopilot_bridge", "perception", "executor", "reasoner", "recorder", "gateway"):
        mod = importlib.import_module(f"services.{name}.settings")
        for obj in vars(mod).values():
            prefix = getattr(getattr(obj, "model_config", {}), "get", lambda *_: None)("env_prefix")
            if isinstance(obj, type) and prefix and prefix.startswith("AERMANI_") and prefix != "AERMANI_":
                classes[prefix] = obj
    for svc_name, svc in SERVICES.items():
        for var in (svc.get("environment") or {}):
            for prefix, cls in classes.items():
                if var.startswith(prefix):
                    field = var[len(prefix):].lower()
                    names = set(cls.model_fields) | {a for f in cls.model_fields.values()
                                                     for a in getattr(f.validation_alias, "choices", ()) or ()}
                    assert field in names or var in names, f"{svc_name}: {var} is not a setting of {cls.__name__}"


def test_the_camera_service_idles_unless_configured():
    """The drone profile carries the camera service; with the sim profile it must not fight the simulator's
    frames, so its source defaults to `none` (publishes nothing) and the simulator's camera stays on."""
    cam = SERVICES["camera"]["environment"]
    assert cam["AERMANI_CAMERA_SOURCE"] == "${AERMANI_CAMERA_SOURCE:-none}"
    assert SERVICES["sim"]["environment"]["AERMANI_SIM_CAMERA"] == "${AERMANI_SIM_CAMERA:-true}"
    from services.camera.settings import CameraSettings

    assert CameraSettings(_env_file=None).source == "none"


# ------------------------------------------------------------------ compose's environment, as the services read it

VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}")


def interpolate(value: object, env: dict[str, str]) -> object:
    """Compose's variable syntax on every string of a parsed file: ${V}, ${V:-default} (unset or empty),
    ${V-default} (unset), ${V:?error} and ${V?error} (a missing variable is an error)."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def one(m: re.Match[str]) -> str:
        name, op, arg = m.group(1), m.group(2) or "", m.group(3) or ""
        have = env.get(name)
        missing = have is None or (op.startswith(":") and have == "")
        if op.endswith("?") and missing:
            raise LookupError(f"{name}: {arg}")
        return (arg if op.endswith("-") else "") if missing else (have or "")

    return VAR.sub(one, value)


def settings_classes() -> dict[str, type]:
    """Every settings class (env prefix -> class): ServiceSettings, the mounts, each service's."""
    import importlib

    from shared.frames import Mount
    from shared.settings import ServiceSettings

    found: dict[str, type] = {"AERMANI_": ServiceSettings, "AERMANI_MOUNT_": Mount}
    for path in sorted((ROOT / "services").glob("*/settings.py")):
        mod = importlib.import_module(f"services.{path.parent.name}.settings")
        for obj in vars(mod).values():
            config = getattr(obj, "model_config", None)
            prefix = config.get("env_prefix") if isinstance(config, dict) else None
            if isinstance(obj, type) and prefix and obj.__module__ == mod.__name__:
                found[prefix] = obj
    return found


def setting_names(cls: type) -> set[str]:
    """The environment variables a settings class reads: prefix + field, and upper-case aliases."""
    prefix = cls.model_config["env_prefix"]  # type: ignore[attr-defined]
    names = set()
    for name, field in cls.model_fields.items():  # type: ignore[attr-defined]
        choices = getattr(field.validation_alias, "choices", None) or ()
        aliases = {c for c in choices if isinstance(c, str) and c.startswith("AERMANI_")}
        names |= aliases or {f"{prefix}{name.upper()}"}
    return names


ALL_SETTINGS = {prefix: setting_names(cls) for prefix, cls in settings_classes().items()}
REAL = set().union(*ALL_SETTINGS.values())
# Variables that are no service's setting, each with the one place it must be used (so this list cannot rot).
COMPOSE_OWN = {"AERMANI_CERTS", "AERMANI_GROUND_ROUTER", "AERMANI_GATEWAY_PUBLISH", "AERMANI_ROUTER_PUBLISH",
               "AERMANI_MAVLINK_PUBLISH", "AERMANI_SERIAL_CGROUP_RULE", "AERMANI_REALSENSE_PACKAGE"}
ELSEWHERE = {  # read by the launcher, the compose test or its script
    "AERMANI_PARENT_PID": "shared/service.py", "AERMANI_COMPOSE_BASE": "tests/compose/test_compose.py",
    "AERMANI_PODMAN_COMPOSE": "tests/compose/test_compose.py", "AERMANI_COMPOSE_STATE": "scripts/compose_test.sh",
    "AERMANI_DEBIAN_MIRROR": "scripts/compose_test.sh",
}
NAME = re.compile(r"\bAERMANI_[A-Z0-9_]*[A-Z0-9]\b")
COMPOSE_TEXT = (ROOT / "docker-compose.yml").read_text()


def test_every_variable_compose_and_the_docs_name_is_real():
    """A misspelt or renamed variable (compose read AERMANI_AUTOPILOT_CONNECTION while the docs said
    AERMANI_AUTOPILOT_BRIDGE_CONNECTION) is silently ignored by pydantic-settings: each name in
    docker-compose.yml, README.md and docs/*.md is a setting of a real class, or one of compose's own used in
    the compose file, or read where ELSEWHERE says; prefixes written as AERMANI_X_* are real prefixes."""
    texts = {"docker-compose.yml": COMPOSE_TEXT, "README.md": (ROOT / "README.md").read_text()}
    texts |= {f"docs/{p.name}": p.read_text() for p in sorted((ROOT / "docs").glob("*.md"))}
    bad = []
    for where, text in texts.items():
        for name in sorted(set(NAME.findall(text))):
            if name in REAL:
                continue
            if name in COMPOSE_OWN:
                assert "${" + name in COMPOSE_TEXT, f"{name} is listed as compose's own but compose never reads it"
                continue
            if name in ELSEWHERE:
                assert name in (ROOT / ELSEWHERE[name]).read_text(), f"{name} is not read in {ELSEWHERE[name]}"
                continue
            owner = max((p for p in ALL_SETTINGS if name.startswith(p)), key=len)
            bad.append(f"{where}: {name} (no setting of {settings_classes()[owner].__name__})")
        for prefix in set(re.findall(r"\bAERMANI_[A-Z0-9_]*_(?=[*` ])", text)):
            if prefix not in ALL_SETTINGS:
                bad.append(f"{where}: prefix {prefix} belongs to no settings class")
    assert not bad, "\n".join(bad)


def test_compose_passes_each_setting_under_its_own_name():
    """One set of names: a service's KEY: ${VAR...} reads the host's variable of the same name."""
    for svc_name, svc in SERVICES.items():
        for key, value in (svc.get("environment") or {}).items():
            for var, _, _ in VAR.findall(str(value)):
                assert var == key, f"{svc_name}: {key} is read from ${{{var}}}: use ${{{key}...}}"


def service_env(name: str, host: dict[str, str]) -> dict[str, str]:
    svc = interpolate(SERVICES[name], host)
    assert isinstance(svc, dict)
    return {k: str(v) for k, v in (svc.get("environment") or {}).items()}


def service_settings(name: str, host: dict[str, str], monkeypatch: pytest.MonkeyPatch):
    """The service's real settings class, built from exactly the environment compose gives it."""
    cls = settings_classes()[f"AERMANI_{name.upper()}_"]
    for var in [v for v in os.environ if v.startswith("AERMANI_")]:
        monkeypatch.delenv(var)
    for var, value in service_env(name, host).items():
        monkeypatch.setenv(var, value)
    return cls(_env_file=None)


def header_command(profile: str) -> dict[str, str]:
    """The variables of the header's example for a profile (`#   drone: A=1 B=2 \\ ... up`)."""
    header = "\n".join(line for line in COMPOSE_TEXT.splitlines() if line.startswith("#"))
    m = re.search(rf"^#\s+{profile}:(.*?--profile {profile} up)", header, re.S | re.M)
    assert m, f"the header has no {profile} command"
    return dict(re.findall(r"(AERMANI_[A-Z0-9_]+)=(\S+)", m.group(1)))


HOST = {"AERMANI_GATEWAY_TOKEN": "x" * 32}


def test_the_headers_drone_command_gets_a_camera_a_serial_bridge_and_tf(monkeypatch):
    from services.autopilot_bridge.link import parse_connection

    host = {**HOST, **header_command("drone")}
    assert host["AERMANI_CAMERA_SOURCE"] == "realsense"
    bridge = service_settings("autopilot_bridge", host, monkeypatch)
    device, baud = parse_connection(bridge.connection, bridge.baud)
    assert device.startswith("/dev/tty") and baud == 921600
    assert bridge.publish_tf == "auto"  # on unless the simulator publishes tf (tests/autopilot_bridge)
    camera = service_settings("camera", host, monkeypatch)
    assert camera.source == "realsense"
    # The camera runs the image with the SDK: the Dockerfile's `camera` target installs the realsense extra.
    build = SERVICES["camera"]["build"]
    assert build["target"] == "camera" and SERVICES["camera"]["image"] != SERVICES["gateway"]["image"]
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM aermani AS camera$", dockerfile, re.M)
    assert re.search(r"^ARG REALSENSE_PACKAGE=pyrealsense2$", dockerfile, re.M)
    assert build["args"]["REALSENSE_PACKAGE"] == "${AERMANI_REALSENSE_PACKAGE-pyrealsense2}"
    assert dockerfile.rstrip().splitlines()[-1] == "FROM aermani", "the default target is every service's image"
    # The flight controller's device reaches the bridge, readable by its user: /dev shared, serial devices
    # (ttyACM 166 for USB) allowed, the dialout group.
    svc = SERVICES["autopilot_bridge"]
    assert "/dev:/dev" in svc["volumes"] and "dialout" in svc["group_add"]
    rules = interpolate(svc["device_cgroup_rules"], host)
    assert {"c 166:* rmw", "c 188:* rmw", "c 4:* rmw"} <= set(rules)  # type: ignore[arg-type]
    rules = interpolate(svc["device_cgroup_rules"], {"AERMANI_SERIAL_CGROUP_RULE": "c 238:* rmw"})
    assert "c 238:* rmw" in rules  # type: ignore[operator]


def test_a_by_path_serial_name_passes_through_compose(monkeypatch):
    from services.autopilot_bridge.link import parse_connection

    by_path = "/dev/serial/by-path/platform-3610000.xhci-usb-0:1.2:1.0"
    host = {**HOST, "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"serial:{by_path}:57600"}
    bridge = service_settings("autopilot_bridge", host, monkeypatch)
    assert parse_connection(bridge.connection, bridge.baud) == (by_path, 57600)


def test_the_simulated_profiles_keep_their_defaults(monkeypatch):
    bridge = service_settings("autopilot_bridge", HOST, monkeypatch)
    assert bridge.connection == "udpin:0.0.0.0:14540" and bridge.publish_tf == "auto"
    # Only PX4's own ids are taken for the autopilot (issue 32; compose passed 0, "whoever comes first").
    assert (bridge.target_system, bridge.target_component) == (1, 1)
    assert bridge.signing_key is None  # no key in the host's environment: signing off, as PX4 without one
    assert service_settings("camera", HOST, monkeypatch).source == "none"
    assert service_settings("sim", HOST, monkeypatch).camera is True


def test_every_python_service_reads_its_compose_environment(monkeypatch):
    """Each service's settings class accepts what compose gives it by default (a bad default would crash the
    container at start), with a crash backoff that keeps podman's immediate restarts from spinning."""
    for name, svc in SERVICES.items():
        if svc.get("image", "").startswith("px4io/") or name.startswith("zenoh-"):
            continue
        s = service_settings(name, HOST, monkeypatch)
        assert s.crash_backoff_s == 30, name


def test_ports_are_published_on_loopback_by_default():
    """Nothing listens beyond the host unless a *_PUBLISH variable says host:port (e.g. 0.0.0.0:7448)."""
    published = [(n, p) for n, s in SERVICES.items() for p in s.get("ports", [])]
    assert published
    for name, port in published:
        host_part = str(interpolate(port, {})).rsplit(":", 1)[0]
        assert host_part.startswith("127.0.0.1:"), (name, port)
        assert VAR.match(port) and VAR.match(port).group(1).endswith("_PUBLISH"), (name, port)  # type: ignore[union-attr]
    moved = interpolate(SERVICES["zenoh-ground"]["ports"][0], {"AERMANI_ROUTER_PUBLISH": "0.0.0.0:7448"})
    assert moved == "0.0.0.0:7448:7448"


def test_compose_passes_every_setting_the_hardware_page_changes():
    """docs/hardware.md's "Settings that change from the simulator": each variable reaches, under its own name,
    a compose service whose settings read it (AERMANI_GROUND_ROUTER is compose's own; AERMANI_ZENOH_CONNECT
    is fixed to the router on loopback)."""
    text = (ROOT / "docs" / "hardware.md").read_text()
    table = text.split("## Settings that change from the simulator", 1)[1].split("\n## ", 1)[0]
    names = set(NAME.findall(table)) - {"AERMANI_GROUND_ROUTER", "AERMANI_ZENOH_CONNECT"}
    assert len(names) >= 12, names
    classes = settings_classes()
    for name in sorted(names):
        readers = [n for n, s in SERVICES.items() if name in (s.get("environment") or {})]
        assert readers, f"{name}: no compose service is given it"
        owner = max((p for p in ALL_SETTINGS if name in ALL_SETTINGS[p]), key=len)
        if owner not in ("AERMANI_", "AERMANI_MOUNT_"):
            service = owner.removeprefix("AERMANI_").removesuffix("_").lower()
            assert service in readers, f"{name} is read by {classes[owner].__name__} but given to {readers}"
