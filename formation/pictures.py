"""Pictures for people: animated GIFs of screens (Pillow). No Ray, no torch."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def upscale(frame: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement of an (H, W, 3) frame."""
    return frame.repeat(factor, axis=0).repeat(factor, axis=1)


def side_by_side(frames: list[np.ndarray], gap: int = 2) -> np.ndarray:
    """Frames of equal height joined left to right with a grey gap."""
    h = frames[0].shape[0]
    bar = np.full((h, gap, 3), 96, np.uint8)
    parts = []
    for i, f in enumerate(frames):
        if i:
            parts.append(bar)
        parts.append(f)
    return np.concatenate(parts, axis=1)


def write_gif(path: str | Path, frames: list[np.ndarray], scale: int = 4, ms_per_frame: int = 120,
              hold_last: int = 6) -> Path:
    """Write an animated GIF that loops, holding the last frame a little longer."""
    from PIL import Image

    if not frames:
        raise ValueError("write_gif: no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(upscale(np.asarray(f, np.uint8), scale)) for f in frames]
    images += [images[-1]] * hold_last
    images[0].save(path, save_all=True, append_images=images[1:], duration=ms_per_frame, loop=0,
                   optimize=False)
    return path


def write_episodes_gif(path: str | Path, episodes: list[list[np.ndarray]], **gif_options) -> Path:
    """Episodes of screens side by side in one GIF; an episode that ends early holds its last screen."""
    longest = max(len(frames) for frames in episodes)
    padded = [frames + [frames[-1]] * (longest - len(frames)) for frames in episodes]
    return write_gif(path, [side_by_side([p[t] for p in padded]) for t in range(longest)], **gif_options)
