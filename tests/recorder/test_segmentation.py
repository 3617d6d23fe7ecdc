"""The simulator's segmentation images stay off the recorder's `**` (a verbatim key chunk): not recorded, and not
asked for, so the simulator does not render them for the recorder; the oracle's runs turn them on."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from services.recorder.service import run
from services.recorder.settings import RecorderSettings
from shared import mcaplog
from tests.helpers import bus_pair, wait_until
from tests.recorder.samples import K, frames

pytestmark = pytest.mark.integration


async def record_frames(router: str, out: Path, segmentation: bool) -> tuple[bool, set[str]]:
    """Run the recorder in this process on `router`, publish three frame sets once it listens, stop it; return
    whether the segmentation key had a subscriber and which keys the file holds."""
    settings = RecorderSettings(out_dir=str(out), health_period_s=0.2, segmentation=segmentation)
    async with bus_pair(router) as (recorder_bus, pub):
        stop = asyncio.Event()
        task = asyncio.create_task(run(recorder_bus, settings, stop))
        await wait_until(lambda: pub.has_subscribers(K.camera_depth), 30, what="the recorder's subscription")
        if segmentation:
            await wait_until(lambda: pub.has_subscribers(K.camera_segmentation), 30, what="segmentation subscriber")
        # Both subscriptions were declared together: once depth matches, the segmentation status is final.
        watched = pub.has_subscribers(K.camera_segmentation)
        for n in range(3):
            for key, data in frames(1_000_000_000 + n, n).items():
                pub.publish(key, data, reliable=True)
        await asyncio.sleep(0.5)
        stop.set()
        await asyncio.wait_for(task, 60)
    (path,) = sorted(out.glob("*.mcap"))
    return watched, {s.key for s in mcaplog.iter_samples(path)}


async def test_segmentation_is_neither_recorded_nor_subscribed_by_default(router: str, tmp_path: Path) -> None:
    watched, keys = await record_frames(router, tmp_path / "rec", segmentation=False)
    assert not watched
    assert K.camera_color.key in keys and K.camera_depth.key in keys
    assert K.camera_segmentation.key not in keys


async def test_segmentation_is_recorded_when_asked(router: str, tmp_path: Path) -> None:
    watched, keys = await record_frames(router, tmp_path / "rec", segmentation=True)
    assert watched
    assert {K.camera_color.key, K.camera_depth.key, K.camera_segmentation.key} <= keys
