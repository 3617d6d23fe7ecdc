"""Autopilot bridge: PX4 over MAVLink (UDP or serial) <-> vehicle state and autopilot commands on Zenoh."""
