# SPDX-License-Identifier: Apache-2.0
"""Alias of :mod:`pugsd.wire.codec` (``from pugsd.wire.messages import decode_grasp_array``)."""

from __future__ import annotations

from pugsd.wire.codec import *  # noqa: F403
from pugsd.wire.codec import (  # explicit for type checkers
    CameraInfoMsg,
    CloudMsg,
    ImageMsg,
    PoseMsg,
    decode_camera_info,
    decode_cloud,
    decode_grasp_array,
    decode_image,
    decode_pose,
    decode_pose_stamped,
    decode_pose_with_covariance,
    decode_status,
    encode_camera_info,
    encode_cloud,
    encode_grasp_array,
    encode_grasp_markers,
    encode_image,
    encode_pose_stamped,
    encode_pose_with_covariance,
    encode_status,
    encode_stereo_infos,
    stereo_rig_from_infos,
)

__all__ = [
    "CameraInfoMsg",
    "CloudMsg",
    "ImageMsg",
    "PoseMsg",
    "decode_camera_info",
    "decode_cloud",
    "decode_grasp_array",
    "decode_image",
    "decode_pose",
    "decode_pose_stamped",
    "decode_pose_with_covariance",
    "decode_status",
    "encode_camera_info",
    "encode_cloud",
    "encode_grasp_array",
    "encode_grasp_markers",
    "encode_image",
    "encode_pose_stamped",
    "encode_pose_with_covariance",
    "encode_status",
    "encode_stereo_infos",
    "stereo_rig_from_infos",
]
