"""Videos of closed-loop episodes with the activation width of every control step shown on the frame.

Frames come from MuJoCo's offscreen renderer (set ``MUJOCO_GL=egl``, or ``osmesa`` with Debian's
``libosmesa6``, on a machine without a display). A ``.gif`` needs only imageio and Pillow; ``.mp4`` needs
the ``imageio-ffmpeg`` package as well.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

# One colour per width, the same in every picture: low widths warm, the fallback grey.
WIDTH_COLOURS = {2: (220, 50, 47), 4: (235, 140, 20), 8: (40, 120, 200), 16: (120, 120, 120)}


def annotate(frame: np.ndarray, bits: int, step: int, label: str) -> np.ndarray:
    """The frame with a bar in the width's colour and the text ``W4A<bits>``, the step and ``label``."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(np.ascontiguousarray(frame))
    draw = ImageDraw.Draw(image)
    width = image.width
    colour = WIDTH_COLOURS.get(bits, (0, 0, 0))
    draw.rectangle([0, 0, width, 18], fill=colour)
    name = "W4A16 (fallback)" if bits == 16 else f"W4A{bits}"
    draw.text((4, 3), f"{name}   step {step}   {label}", fill=(255, 255, 255))
    return np.asarray(image)


def record_episode(runner, task: str, config: str, seed: int, path: str | os.PathLike, *,
                   camera: str = "frontview", size: int = 256, skip: int = 1, fps: int = 20):
    """Runs one episode with an offscreen renderer and writes it to ``path`` (``.gif`` or ``.mp4``);
    every ``skip``-th step becomes a frame (robomimic's ``video_skip``). Returns the episode."""
    import imageio

    from . import envs
    from .rollout import run_episode

    path = Path(path)
    if path.suffix not in (".gif", ".mp4"):
        raise ValueError(f"video path must end in .gif or .mp4, got {path}")
    os.environ.setdefault("MUJOCO_GL", "egl")
    env = envs.make_env(task, render=True)
    frames: list[np.ndarray] = []
    episode = run_episode(runner, task, config, seed, env=env, frames=frames, camera=camera, frame_size=size)
    outcome = "success" if episode.success else "running"
    annotated = [annotate(frame, episode.bits[t], t, f"{config} {outcome if t == episode.steps - 1 else ''}")
                 for t, frame in enumerate(frames) if t % skip == 0]
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gif":
        imageio.mimsave(path, annotated, duration=1000 * skip / fps, loop=0)
    else:
        imageio.mimsave(path, annotated, fps=fps / skip)
    return episode
