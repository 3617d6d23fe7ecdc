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
    for name, svc in SERVICES.items():
        env = svc.get("environment", {})
        endpoint = env.get("AERMANI_ZENOH_CONNECT")
        if endpoint is None:
            continue
        router = re.match(r"tcp/([\w-]+):\d+", endpoint).group(1)
        assert router in SERVICES, (name, endpoint)
        profiles = set(svc["profiles"])
        router_profiles = set(SERVICES[router]["profiles"])
        # A service either shares its router's profile or is meant to run beside it (sim rides on drone).
        assert profiles & router_profiles or (profiles == {"sim"} and "drone" in router_profiles), name


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
    assert "--connect" in cmd and "AERMANI_GROUND_ROUTER" in cmd[cmd.index("--connect") + 1]


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
