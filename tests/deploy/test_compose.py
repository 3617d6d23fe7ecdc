"""The compose file, checked without a Docker engine: every service command names a real module, every
profile is complete, required secrets are required, and the Dockerfile installs what Open3D needs."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

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
    assert "${AERMANI_ROUTER_PUBLISH:-7448}:7448" in ground_ports
    assert not any(p.split(":")[-1].startswith("7447") for p in ground_ports)
    assert "ports" not in SERVICES["zenoh-drone"] or all("7447" not in p for p in SERVICES["zenoh-drone"]["ports"])
    # The bridge's MAVLink port reaches the host's loopback only (the bridge locks onto the first autopilot).
    assert SERVICES["zenoh-drone"]["ports"] == ["127.0.0.1:${AERMANI_MAVLINK_PUBLISH:-14540}:14540/udp"]


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
