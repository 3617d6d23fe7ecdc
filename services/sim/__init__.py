"""The built-in simulator (MuJoCo). MuJoCo picks its OpenGL platform when first imported: headless EGL unless
MUJOCO_GL says otherwise (osmesa for pure-software rendering)."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
