# One image for every aermani service; the compose file picks the module with `command`.
FROM python:3.11-slim-bookworm

# Open3D links libusb, libGL/EGL and X11 even when headless; OpenCV/Open3D need libgomp. MuJoCo (the
# simulator) renders headless through EGL on Mesa's software rasterizer, or OSMesa with MUJOCO_GL=osmesa.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri \
    libosmesa6 libgomp1 libx11-6 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN pip install --no-cache-dir .

ENV PYTHONUNBUFFERED=1 \
    MUJOCO_GL=egl \
    AERMANI_ZENOH_CONNECT=tcp/127.0.0.1:7447
# Unprivileged at run time; serial access for the bridge is granted with `group_add: dialout`.
RUN useradd --create-home --uid 1000 aermani && mkdir -p /data && chown aermani /data
USER aermani
ENTRYPOINT ["python", "-m"]
CMD ["services.gateway"]
