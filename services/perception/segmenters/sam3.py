"""`sam3` segmenter: Meta SAM3 (promptable concept segmentation) through Hugging Face transformers."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any

import numpy as np

from services.perception import query as q
from services.perception.frames import Frame
from services.perception.segmenters.base import Found, Segment, Segmenter, register
from shared.errors import PerceptionError

INSTALL = ("install the optional extra with `.venv/bin/pip install -e '.[sam3]'` (torch, transformers>=4.57, "
           "pillow) and put the weights in the Hugging Face cache (`huggingface-cli download facebook/sam3`, "
           "gated: accept the licence first) or set AERMANI_PERCEPTION_SAM3_MODEL to a local directory; "
           "or choose another segmenter with AERMANI_PERCEPTION_SEGMENTER=color (or sim in the simulator)")

# What the prompt names for detections: SAM3 segments concepts, so detections prompt a fixed list.
DEFAULT_PROMPTS = ("cup", "can", "bottle", "box", "apple", "orange", "banana", "wrench", "screwdriver", "hammer",
                   "table", "shelf", "sink", "counter")


def _missing_modules() -> list[str]:
    return [m for m in ("torch", "transformers", "PIL") if importlib.util.find_spec(m) is None]


@register
class Sam3Segmenter(Segmenter):
    """Text prompt -> instance masks. Loaded at start (the service refuses to start without it; it is
    never silently replaced by another segmenter). Weights are only read locally: no download at run time."""

    type = "sam3"

    model: Any = None
    processor: Any = None
    device: str = "cpu"

    def start(self) -> None:
        missing = _missing_modules()
        if missing:
            raise PerceptionError(f"segmenter sam3 needs {', '.join(missing)}, which is not installed: {INSTALL}")
        import torch
        import transformers

        if not hasattr(transformers, "Sam3Model"):
            raise PerceptionError(f"transformers {transformers.__version__} has no Sam3Model (needs >= 4.57): "
                                  f"{INSTALL}")
        src = self.settings.sam3_model
        local = Path(src).expanduser()
        try:
            kwargs = {} if local.is_dir() else {"local_files_only": True}
            self.processor = transformers.Sam3Processor.from_pretrained(str(local) if local.is_dir() else src, **kwargs)
            self.model = transformers.Sam3Model.from_pretrained(str(local) if local.is_dir() else src, **kwargs)
        except (OSError, ValueError) as exc:
            raise PerceptionError(
                f"SAM3 weights not found at {src!r} ({type(exc).__name__}: {exc}); {INSTALL}") from exc
        dev = self.settings.sam3_device
        self.device = ("cuda" if torch.cuda.is_available() else "cpu") if dev == "auto" else dev
        self.model.to(self.device).eval()
        os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

    def known_names(self, frame: Frame | None) -> list[str]:
        return list(DEFAULT_PROMPTS)

    def _segment(self, frame: Frame, prompt: str, key0: int = 0) -> list[Segment]:
        import torch
        from PIL import Image

        image = Image.fromarray(frame.rgb)
        inputs = self.processor(images=image, text=prompt, return_tensors="pt").to(self.device)
        with torch.no_grad():
            outputs = self.model(**inputs)
        res = self.processor.post_process_instance_segmentation(
            outputs, threshold=self.settings.sam3_threshold, mask_threshold=0.5,
            target_sizes=inputs.get("original_sizes").tolist())[0]
        out = []
        for i, (mask, score) in enumerate(zip(res["masks"], res["scores"], strict=False)):
            idx = np.flatnonzero(np.asarray(mask.cpu() if hasattr(mask, "cpu") else mask, dtype=bool).ravel())
            if idx.size < self.settings.min_pixels:
                continue
            cat = "surface" if prompt in ("table", "shelf", "sink", "counter") else "object"
            out.append(Segment(key0 + i, prompt, cat, "", float(score), 0.0, int(idx.size), _indices=idx))
        return out

    def detect(self, frame: Frame) -> list[Segment]:
        out: list[Segment] = []
        for p in DEFAULT_PROMPTS:
            out.extend(self._segment(frame, p, key0=len(out) * 1000))
        return out

    def find(self, frame: Frame, query: q.Query, categories: tuple[str, ...]) -> Found:
        prompt = " ".join(w for w in query.words if w not in q.SIZE_WORDS) or query.text
        segs = self._segment(frame, prompt)
        if not segs:
            return Found(None, "not_visible", f"SAM3 found no '{prompt}' in view")
        if len(segs) > 1 and query.size is not None:
            seg = (max if query.size == "larger" else min)(segs, key=lambda s: s.n_pixels)
            return Found(seg, "ok", f"{query.size} of {len(segs)} '{prompt}' (by image area)")
        best = max(segs, key=lambda s: s.score)
        if len(segs) > 1 and sorted(s.score for s in segs)[-2] > best.score - 0.05:
            return Found(None, "ambiguous", f"SAM3 found {len(segs)} '{prompt}' with similar scores; say which")
        return Found(best, "ok", f"SAM3 '{prompt}' score {best.score:.2f}")
