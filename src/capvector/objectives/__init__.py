"""Loss modules attached to a VLAModule by callbacks: auxiliary objectives and regularisers."""

from capvector.objectives.base import Objective

__all__ = ["Objective"]
