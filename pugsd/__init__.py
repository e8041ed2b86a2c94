# SPDX-License-Identifier: Apache-2.0
"""pugsd: a real-time perception daemon implementing PUGS (Perceptual Uncertainty for Grasp Selection)."""

__version__ = "0.1.0"
