"""Settings of the perception service (env AERMANI_PERCEPTION_*)."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.settings import ServiceSettings


class PerceptionSettings(ServiceSettings):
    """Perception configuration (AERMANI_PERCEPTION_*): segmenter type, its model or catalogue, workers."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_PERCEPTION_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    segmenter: str = "color"
    """Segmenter type: color (OpenCV colour classes on the camera's pixels + depth; the default, no GPU), sam3
    (Meta SAM3 via transformers; install with `pip install -e .[sam3]`) or sim (the simulator's ground-truth
    instance masks: an opt-in oracle for debugging and upper-bound evaluations, never real perception)."""
    detections_hz: float = Field(5.0, ge=0.0, le=30.0)
    """Rate of perception/detections (0 disables); never faster than frames arrive."""
    frame_wait_s: float = Field(0.5, ge=0.0, le=5.0)
    """When the newest frame is older than a request's max_frame_age_s, wait this long for a fresh one."""
    min_pixels: int = Field(30, ge=1)
    """Masks with fewer pixels count as not visible."""
    min_points: int = Field(30, ge=3)
    """Fewer valid 3D points than this -> too_few_points."""
    rim_px: int = Field(2, ge=0, le=8)
    """An object mask's rim this many pixels wide loses the pixels whose depth does not continue the mask's
    interior (by 2 % + 2 cm): an RGB-D camera's depth sits a pixel or two off the colour the mask is drawn on
    (`realistic` 1 px, `harsh` 2 px), so the rim carries depths of what lies behind or in front of the object.
    0: every mask pixel."""
    max_object_points: int = Field(3000, ge=100)
    """Object clouds are evenly subsampled to this many points (latency bound)."""
    max_surface_points: int = Field(12000, ge=500)
    """Surface clouds are evenly subsampled to this many points before RANSAC."""
    clutter_stride: int = Field(3, ge=1, le=16)
    """Pixel stride of the whole-image cloud used to find clutter on a surface."""
    plane_distance: float = Field(0.012, gt=0.0)
    """RANSAC inlier distance for surface planes, metres."""
    max_plane_tilt_deg: float = Field(10.0, gt=0.0, le=45.0)
    """Planes tilted more than this from horizontal are not placement surfaces."""
    cell_size: float = Field(0.02, gt=0.004, le=0.1)
    """Grid cell for the free-spot search, metres."""
    vertical_offset: float = Field(0.02, ge=0.0, le=0.3)
    """Release height of the held object's bottom above the surface, metres."""
    placement_margin: float = Field(0.03, ge=0.0)
    """Extra clearance beyond the held object's half-diagonal, metres."""
    default_object_radius: float = Field(0.06, gt=0.0)
    """Held-object footprint radius assumed when a placement request gives no object_size, metres."""
    workers: int = Field(1, ge=1, le=8)
    """Threads for the numerical work (requests queue behind each other beyond this)."""
    sam3_model: str = "facebook/sam3"
    """SAM3 weights: a local directory or a Hugging Face hub id already in the local cache (no download)."""
    sam3_device: str = "auto"
    """auto (cuda when available), cuda or cpu."""
    sam3_threshold: float = Field(0.5, ge=0.0, le=1.0)
    """Minimum SAM3 instance score."""
    color_min_area_px: int = Field(60, ge=1)
    """Colour blobs smaller than this are ignored."""
    color_catalog: str = ""
    """JSON file with the colour segmenter's object and surface classes (empty: the simulator's objects)."""
