"""A ROS 2 peer the project did not write: zenoh-ros2-sdk (a PyPI implementation of rmw_zenoh's wire format,
"use ROS 2 without ROS 2") in its own process, as a ROS 2 user's node would be.

    python tests/ros2/sdk_peer.py listen PORT MSGDIR COUNT TOPIC=TYPE...   one JSON line per message received
    python tests/ros2/sdk_peer.py call PORT MSGDIR SERVICE TYPE COMMAND      one JSON line: the response
    python tests/ros2/sdk_peer.py graph PORT MSGDIR                          the ROS graph's topics and services

The SDK finds message definitions in MSGDIR (<pkg>/msg/<Name>.msg, <pkg>/srv/<Name>.srv) and computes each
type's hash from them itself; it would clone ROS 2's interface repositories from GitHub for a type missing
there, so the tests hand it every definition it needs (no test reaches the internet).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any


def summary(msg: Any) -> dict[str, Any]:
    """What a test checks of a decoded message (arrays by size, nested messages by their fields)."""
    out: dict[str, Any] = {}
    for name in getattr(msg, "__dataclass_fields__", {}):
        value = getattr(msg, name)
        if hasattr(value, "__dataclass_fields__"):
            out[name] = summary(value)
        elif hasattr(value, "shape"):  # a numpy array: its size, its first bytes, small ones whole
            out[name] = {"len": int(value.size), "head": value[:4].tobytes().hex() if value.dtype.itemsize == 1
                         else "", "values": value.tolist() if value.size <= 64 else []}
        elif isinstance(value, list):
            out[name] = [summary(v) for v in value]
        elif isinstance(value, bytes):
            out[name] = {"len": len(value)}
        else:
            out[name] = value
    return out


def main(argv: list[str]) -> int:
    mode, port, msgdir = argv[0], int(argv[1]), argv[2]
    from zenoh_ros2_sdk import message_registry

    message_registry._registry = message_registry.MessageRegistry(msgdir)  # the SDK's one registry
    if mode == "listen":
        from zenoh_ros2_sdk import ROS2Subscriber

        count = int(argv[3])
        left = {}
        lock = threading.Lock()
        subs = []
        for spec in argv[4:]:
            topic, ros_type = spec.split("=")
            left[topic] = count

            def on(msg: Any, topic: str = topic) -> None:
                with lock:
                    if left[topic] <= 0:
                        return
                    left[topic] -= 1
                    print(json.dumps({"topic": topic, "msg": summary(msg)}, default=str), flush=True)

            subs.append(ROS2Subscriber(topic, ros_type, on, router_port=port, node_name="sdk_listener"))
        print(json.dumps({"ready": sorted(left)}), flush=True)
        while any(n > 0 for n in left.values()):
            time.sleep(0.05)
        for s in subs:
            s.close()
        return 0
    if mode == "call":
        from zenoh_ros2_sdk import ROS2ServiceClient

        service, srv_type, command = argv[3], argv[4], argv[5]
        client = ROS2ServiceClient(service, srv_type, router_port=port, node_name="sdk_caller", timeout=30.0)
        print(json.dumps({"ready": service, "key": client.keyexpr}), flush=True)
        reply = client.call(command=command, t_max_s=0.0)
        print(json.dumps({"reply": None if reply is None else summary(reply)}), flush=True)
        return 0
    if mode == "graph":
        from zenoh_ros2_sdk import get_service_names_and_types, get_topic_names_and_types

        deadline = time.monotonic() + 30
        while True:  # discovery reads liveliness tokens: the bridge's may take a moment to reach a new peer
            topics = {name: types[0] for name, types in get_topic_names_and_types(router_port=port)}
            services = {name: types[0] for name, types in get_service_names_and_types(router_port=port)}
            if topics and services or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        print(json.dumps({"topics": topics, "services": services}), flush=True)
        return 0
    print(f"unknown mode {mode}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
