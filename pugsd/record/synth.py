# SPDX-License-Identifier: Apache-2.0
"""Synthetic recordings: stereo sequences written as the daemon would record its inputs.

Each frame becomes left/right ``Image`` (``rgb8`` or ``mono8``), left/right ``CameraInfo``, the
camera pose (``PoseWithCovarianceStamped``) and, when present, the object mask (``mono8``, 255 on
the object), on the ``[topics]`` topics and keys. Frames come from the synthetic world
(:func:`pugsd.sim.sequence.make_sequence`: ``complete``, ``partial``, ``noisy_partial``) or
from any list of :class:`StereoFrame`.
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pugsd.config import TopicsConfig
from pugsd.core.types import StereoFrame
from pugsd.record.mcapio import ChannelTable, file_error, new_writer, versions
from pugsd.wire import codec
from pugsd.wire.topics import ROLE_TYPES, key_for

KINDS = ("complete", "partial", "noisy_partial")


@dataclass(frozen=True, slots=True)
class WireMessage:
    role: str
    topic: str
    typename: str
    key: str
    data: bytes
    stamp_ns: int


def frame_messages(
    frame: StereoFrame,
    topics: TopicsConfig | None = None,
    *,
    left_frame_id: str = "left_camera",
    right_frame_id: str = "right_camera",
    world_frame_id: str = "world",
) -> list[WireMessage]:
    """The wire messages of one stereo frame (pose first, then infos, images, mask)."""
    t = topics or TopicsConfig()
    st = int(frame.stamp_ns)
    li, ri = codec.encode_stereo_infos(frame.rig, st, left_frame_id, right_frame_id)
    enc = "mono8" if frame.left.ndim == 2 else "rgb8"
    out: list[tuple[str, bytes]] = [
        (
            "pose",
            codec.encode_pose_with_covariance(st, frame.T_W_C, frame.pose_cov, world_frame_id),
        ),
        ("left_info", li),
        ("right_info", ri),
        ("left_image", codec.encode_image(frame.left, st, left_frame_id, enc)),
        ("right_image", codec.encode_image(frame.right, st, right_frame_id, enc)),
    ]
    if frame.mask is not None:
        m = np.where(np.asarray(frame.mask, dtype=bool), 255, 0).astype(np.uint8)
        out.append(("mask", codec.encode_image(m, st, left_frame_id, "mono8")))
    return [WireMessage(r, getattr(t, r), ROLE_TYPES[r], key_for(t, r), d, st) for r, d in out]


def write_recording(
    path: str | Path,
    frames: Iterable[StereoFrame],
    topics: TopicsConfig | None = None,
    *,
    t0_ns: int = 1_700_000_000_000_000_000,
    chunk_size: int = 1 << 20,
    metadata: Mapping[str, Mapping[str, str]] | None = None,
) -> int:
    """Write ``frames`` as an MCAP recording. Stamps are kept; ``log_time`` is ``t0_ns + stamp``
    plus a microsecond per message within a frame, ``publish_time`` likewise. Returns the number
    of messages."""
    p = Path(path)
    n = 0
    tmp = p.with_name(p.name + ".part")
    try:
        f = open(tmp, "wb")  # noqa: SIM115 (closed by the with below)
    except OSError as exc:
        raise file_error(p, exc, "cannot write") from None
    with f:
        w = new_writer(f, chunk_size)
        table = ChannelTable(w)
        w.add_metadata("pugsd.versions", versions())
        w.add_metadata("pugsd.synthetic", {"generator": "pugsd.record.synth"})
        for name, md in (metadata or {}).items():
            w.add_metadata(name, dict(md))
        for frame in frames:
            for j, m in enumerate(frame_messages(frame, topics)):
                lt = t0_ns + m.stamp_ns + 1000 * j
                w.add_message(table.channel_id(m.topic, m.typename, m.key), lt, m.data, lt, n + 1)
                n += 1
        w.finish()
    tmp.replace(p)
    return n


def synthetic_frames(
    kind: str = "partial",
    object_name: str = "mug",
    n_frames: int | None = None,
    width: int = 160,
    height: int = 120,
    seed: int = 0,
    **kwargs: Any,
) -> tuple[list[StereoFrame], dict[str, str]]:
    """Frames of a synthetic sequence (``complete``, ``partial`` or ``noisy_partial``) from the
    synthetic world, and a metadata map describing it (incl. the pipeline overrides it implies)."""
    # imported lazily: the synthetic world is heavy (trimesh, open3d) and optional here
    make_sequence = importlib.import_module("pugsd.sim.sequence").make_sequence
    seq = make_sequence(object_name, kind, n_frames, width, height, seed, **kwargs)
    md = {
        "object": seq.object_name,
        "trajectory": seq.trajectory,
        "pose": seq.pose,
        "seed": str(seq.seed),
        "frames": str(len(seq.frames)),
        "width": str(width),
        "height": str(height),
        "core_overrides": json.dumps(seq.core_overrides, sort_keys=True),
        "T_W_O": json.dumps(np.asarray(seq.T_W_O).tolist()),
    }
    return seq.frames, md


def generate(
    path: str | Path,
    kind: str = "partial",
    object_name: str = "mug",
    n_frames: int | None = None,
    width: int = 160,
    height: int = 120,
    seed: int = 0,
    topics: TopicsConfig | None = None,
) -> int:
    """Render a synthetic sequence and write it as a recording; returns the message count."""
    frames, md = synthetic_frames(kind, object_name, n_frames, width, height, seed)
    return write_recording(path, frames, topics, metadata={"pugsd.scene": md})
