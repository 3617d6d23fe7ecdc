# One image for every aermani service; the compose file picks the module with `command`.
# BASE: any Debian bookworm image with python3 (3.11) and its venv module. Without a container registry, build
# one with debootstrap (scripts/compose_test.sh does; docs/deploy.md explains).
# Targets: the default (the last stage) is the image of every service; `camera` adds the RealSense SDK for the
# camera service (compose builds it for `camera`).
ARG BASE=python:3.11-slim-bookworm
FROM ${BASE} AS aermani

# Open3D links libusb, libGL/EGL and X11 even when headless; OpenCV/Open3D need libgomp. MuJoCo (the
# simulator) renders headless through EGL on Mesa's software rasterizer, or OSMesa with MUJOCO_GL=osmesa.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri \
    libosmesa6 libgomp1 libx11-6 \
 && rm -rf /var/lib/apt/lists/*

# A venv: the same layout on python:*-slim and on a Debian base whose system pip refuses installs (PEP 668).
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH

# pip's index, extra indexes, find-links, constraints and CA bundle for builds behind a proxy or a mirror
# (pip ignores the empty ones). Paths they name must exist in the build: COPY them or mount them (`podman
# build -v`), see docs/deploy.md.
ARG PIP_INDEX_URL= PIP_EXTRA_INDEX_URL= PIP_TRUSTED_HOST= PIP_FIND_LINKS= PIP_CERT= PIP_CONSTRAINT=
WORKDIR /app
COPY pyproject.toml ./
# The dependencies first, in a layer that changes only with pyproject.toml (the package is installed empty
# and removed again): a code change then rebuilds in seconds instead of reinstalling Open3D and MuJoCo.
RUN mkdir -p shared services aermani && touch README.md && pip install --no-cache-dir . && pip uninstall -y -q aermani \
 && rm -rf shared services aermani build
COPY README.md ./
COPY shared ./shared
COPY services ./services
COPY aermani ./aermani
RUN pip install --no-cache-dir --no-deps .

ENV PYTHONUNBUFFERED=1 \
    MUJOCO_GL=egl \
    AERMANI_ZENOH_CONNECT=tcp/127.0.0.1:7447
# Unprivileged at run time; serial access for the bridge is granted with `group_add: dialout`. The volume
# mount points exist and belong to uid 1000 so new named volumes start owned by it (Docker and podman copy
# the mount point's ownership into an empty volume).
RUN useradd --create-home --uid 1000 aermani && mkdir -p /data/logs && chown -R aermani /data
USER aermani
ENTRYPOINT ["python", "-m"]
CMD ["services.gateway"]

# The camera service's image: the above plus pyrealsense2 (librealsense; it reaches the camera through libusb,
# installed above, on the host's /dev that compose shares with the USB device rule). PyPI has wheels for x86_64;
# for a Jetson (aarch64) pass a pyrealsense2 you built or found as REALSENSE_PACKAGE (a wheel URL or an index's
# name, with PIP_EXTRA_INDEX_URL), or REALSENSE_PACKAGE= (empty) for an image without it (the realsense source
# then says what to install). The ZED SDK needs NVIDIA's runtime and is not here (docs/hardware.md).
FROM aermani AS camera
ARG REALSENSE_PACKAGE=pyrealsense2
ARG PIP_INDEX_URL= PIP_EXTRA_INDEX_URL= PIP_TRUSTED_HOST= PIP_FIND_LINKS= PIP_CERT= PIP_CONSTRAINT=
USER root
RUN if [ -n "$REALSENSE_PACKAGE" ]; then \
      pip install --no-cache-dir "$REALSENSE_PACKAGE" || { echo "no $REALSENSE_PACKAGE for $(uname -m) here: pass \
--build-arg REALSENSE_PACKAGE=<a pyrealsense2 wheel for this platform>, or REALSENSE_PACKAGE= to build without it \
(compose: AERMANI_REALSENSE_PACKAGE)" >&2; exit 1; }; \
      python -c "import pyrealsense2"; \
    fi
USER aermani

# The default target: every service's image.
FROM aermani
