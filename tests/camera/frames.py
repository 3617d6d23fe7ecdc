"""Camera test material written to disk: image folders with 16-bit depth PNGs and a calibration YAML, and
aermani MCAP logs with camera samples."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from mcap.writer import CompressionType, Writer

from shared.keys import Keys
from shared.mcaplog import ChannelTable
from shared.sensors import Intrinsics, calibration_message, color_message, depth_message

CAL = Intrinsics(width=320, height=240, fx=175.0, fy=175.0, cx=159.5, cy=119.5)


def frame_pixels(i: int, width: int = 320, height: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """RGB with a red square that moves with `i`; depth in 8x8 blocks (exact under nearest resizing)."""
    rgb = np.full((height, width, 3), 90, np.uint8)
    x = 40 + 20 * i
    rgb[100:140, x:x + 40] = (220, 30, 30)
    blocks = (1000 + 100 * i + np.arange(height // 8)[:, None] * 10 + np.arange(width // 8)[None, :]).astype(np.uint16)
    depth = np.kron(blocks, np.ones((8, 8), np.uint16))
    return rgb, depth


def write_folder(folder: Path, n: int = 4, depth: bool = True, calibration: bool = True,
                 layout: str = "flat") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    cdir, ddir = (folder / "color", folder / "depth") if layout == "split" else (folder, folder)
    cdir.mkdir(exist_ok=True)
    ddir.mkdir(exist_ok=True)
    for i in range(n):
        rgb, d = frame_pixels(i)
        cv2.imwrite(str(cdir / f"{i:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if depth:
            cv2.imwrite(str(ddir / (f"{i:04d}.png" if layout == "split" else f"{i:04d}_depth.png")), d)
    if calibration:
        (folder / "calibration.yaml").write_text(
            f"width: {CAL.width}\nheight: {CAL.height}\nfx: {CAL.fx}\nfy: {CAL.fy}\ncx: {CAL.cx}\ncy: {CAL.cy}\n")
    return folder


def write_log(path: Path, n: int = 5, vehicle: str = "am7", depth: bool = True) -> list[int]:
    """An aermani MCAP log (the recorder's channel conventions) with n colour/depth pairs + calibration;
    depth is written before colour on odd frames, as Zenoh may deliver them. Returns the recorded stamps."""
    keys = Keys(vehicle)
    stamps = [1_700_000_000_000_000_000 + i * 66_000_000 for i in range(n)]
    with path.open("wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="", library="aermani-test")
        table = ChannelTable(w)

        def put(key: str, schema: str, data: bytes, t: int) -> None:
            cid = table.channel_id(key, f"application/protobuf;{schema}")
            w.add_message(cid, t, data, t, table.next_sequence(cid))

        put(keys.camera_calibration, "foxglove.CameraCalibration", calibration_message(CAL, stamps[0]), stamps[0])
        for i, t in enumerate(stamps):
            rgb, d = frame_pixels(i)
            color = (keys.camera_color, "foxglove.CompressedImage", color_message(rgb, t, quality=95), t)
            dep = (keys.camera_depth, "foxglove.CompressedImage", depth_message(d, t), t + 1000)
            order = [dep, color] if i % 2 else [color, dep]
            for item in order:
                if item is dep and not depth:
                    continue
                put(*item)
        w.finish()
    return stamps
