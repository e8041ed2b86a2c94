# SPDX-License-Identifier: Apache-2.0
"""Wire format: ROS 2 CDR messages on rmw_zenoh-compatible zenoh keys with rmw_zenoh attachments.

Modules: :mod:`types` (typestore with pugs_msgs), :mod:`codec` (encode/decode), :mod:`keys`,
:mod:`topics` (TopicsConfig roles), :mod:`attachment`, :mod:`publisher`, :mod:`session`.
"""

from __future__ import annotations

from pugsd.wire.attachment import Attachment, decode_attachment, encode_attachment, new_gid
from pugsd.wire.codec import (
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
from pugsd.wire.keys import KeyInfo, parse_key, subscription_key, topic_key
from pugsd.wire.publisher import Publisher
from pugsd.wire.session import (
    asyncio_bridge,
    asyncio_bridge_map,
    check_loopback_safe,
    close_session,
    loopback_config,
    open_session,
)

__all__ = [
    "Attachment",
    "CameraInfoMsg",
    "CloudMsg",
    "ImageMsg",
    "KeyInfo",
    "PoseMsg",
    "Publisher",
    "asyncio_bridge",
    "asyncio_bridge_map",
    "check_loopback_safe",
    "close_session",
    "decode_attachment",
    "decode_camera_info",
    "decode_cloud",
    "decode_grasp_array",
    "decode_image",
    "decode_pose",
    "decode_pose_stamped",
    "decode_pose_with_covariance",
    "decode_status",
    "encode_attachment",
    "encode_camera_info",
    "encode_cloud",
    "encode_grasp_array",
    "encode_grasp_markers",
    "encode_image",
    "encode_pose_stamped",
    "encode_pose_with_covariance",
    "encode_status",
    "encode_stereo_infos",
    "loopback_config",
    "new_gid",
    "open_session",
    "parse_key",
    "stereo_rig_from_infos",
    "subscription_key",
    "topic_key",
]
