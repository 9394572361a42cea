"""First-frame prompts of the tissue segmentation: a box and/or points on and off the tissue.

A `Prompt` comes from the command line (`Prompt.parse`), the recording's metadata (`prompt_box`,
`Prompt.from_box`) or a detector (`vfdata.recon.detector.DetectorPrompt`). Coordinates are pixels of
the full-resolution left image.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from vfdata.errors import InputError


@dataclass(frozen=True)
class Prompt:
    """A first-frame prompt in pixels: `box` (x0, y0, x1, y1) and/or points on the tissue
    (`positive`) and off it (`negative`)."""

    box: tuple[float, float, float, float] | None = None
    positive: tuple[tuple[float, float], ...] = ()
    negative: tuple[tuple[float, float], ...] = ()

    def __post_init__(self):
        if self.box is None and not self.positive:
            raise InputError("prompt", "needs a box or at least one positive point")
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            if not (x1 > x0 and y1 > y0):
                raise InputError(
                    "prompt", f"box {list(self.box)} must be x0,y0,x1,y1 with x1 > x0 and y1 > y0"
                )

    @classmethod
    def parse(cls, text: str) -> Prompt:
        """Parse "box:x0,y0,x1,y1", "points:x,y;x,y" (on the tissue) and "neg:x,y;x,y" (off it),
        several joined by spaces, e.g. "box:100,80,400,300 neg:250,200"."""
        box = None
        positive: list[tuple[float, float]] = []
        negative: list[tuple[float, float]] = []
        parts = [p for p in re.split(r"[\s|]+", text.strip()) if p]
        if not parts:
            raise InputError(
                "prompt", "empty prompt (expected e.g. 'box:100,80,400,300' or 'points:320,240')"
            )
        for part in parts:
            kind, _, values = part.partition(":")
            kind = kind.lower()
            try:
                if kind == "box":
                    numbers = [float(v) for v in values.split(",")]
                    if len(numbers) != 4:
                        raise ValueError
                    box = (numbers[0], numbers[1], numbers[2], numbers[3])
                elif kind in ("points", "pos", "point"):
                    positive += _parse_points(values)
                elif kind in ("neg", "negative"):
                    negative += _parse_points(values)
                else:
                    raise InputError("prompt", f"unknown part '{part}' (use box:, points: or neg:)")
            except ValueError:
                raise InputError(
                    "prompt", f"cannot read '{part}' (e.g. box:100,80,400,300 or points:320,240;300,200)"
                ) from None
        return cls(box=box, positive=tuple(positive), negative=tuple(negative))

    @classmethod
    def from_box(cls, box: Sequence[float]) -> Prompt:
        if len(box) != 4:
            raise InputError("prompt", f"a box has 4 numbers x0,y0,x1,y1, not {len(box)}")
        return cls(box=tuple(float(v) for v in box))  # type: ignore[arg-type]

    def check_inside(self, width: int, height: int) -> None:
        """Raise InputError if any part of the prompt lies outside a width x height image."""

        def inside(x: float, y: float) -> bool:
            return 0 <= x <= width - 1 and 0 <= y <= height - 1

        if self.box is not None:
            # Box corners are continuous coordinates: the far edge may sit on the image border.
            x0, y0, x1, y1 = self.box
            if not (0 <= x0 and 0 <= y0 and x1 <= width and y1 <= height):
                raise InputError("prompt", f"box {list(self.box)} is outside the {width}x{height} image")
        for x, y in self.positive + self.negative:
            if not inside(x, y):
                raise InputError("prompt", f"point ({x:g}, {y:g}) is outside the {width}x{height} image")

    def to_dict(self) -> dict:
        return {
            "box": list(self.box) if self.box else None,
            "positive": [list(p) for p in self.positive],
            "negative": [list(p) for p in self.negative],
        }


def _parse_points(values: str) -> list[tuple[float, float]]:
    points = []
    for pair in values.split(";"):
        numbers = [float(v) for v in pair.split(",")]
        if len(numbers) != 2:
            raise ValueError
        points.append((numbers[0], numbers[1]))
    return points
