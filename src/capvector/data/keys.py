"""Names of the fields in a training batch and in a dataset sample.

Every dataset yields a dict with these keys and every backbone reads them, so a backbone never
depends on where the data came from (HDF5, LeRobot, a live simulator).
"""

IMAGES = "images"
"""(B, N_cam, 3, H, W) float32 in [0, 1], upright, cameras in ``DataSpec.cameras`` order."""

PROPRIO = "proprio"
"""(B, P) float32, normalised with the dataset's q01/q99 statistics by the family's rule
(``capvector.data.statistics``: clipped to [-1, 1] for OpenVLA-OFT, not clipped for Pi0.5)."""

ACTIONS = "actions"
"""(B, T, A) float32: the action chunk, normalised as ``PROPRIO`` (OFT leaves the gripper raw)."""

INSTRUCTION = "instruction"
"""list[str] of length B: the task's language instruction."""

DEPTH = "depth"
"""(B, N_cam, H, W) float32 depth in metres (optional, for geometric teachers)."""

INTRINSICS = "intrinsics"
"""(B, N_cam, 3, 3) float32 pinhole intrinsics in pixels of the stored image (optional)."""

ANNOTATION = "annotation"
"""list[str] of length B: a text answer about the scene at this step (optional, for reasoning)."""

INDEX = "index"
"""(B,) int64: each sample's position in its dataset (``dataset[i]``)."""

NOISE_SEED = "noise_seed"
"""(B,) int64: a per-sample seed for the training noise of flow-matching backbones (ε and t).
``RobotDataModule`` sets it while training, from (``data.seed``, epoch, ``INDEX``), so a sample
draws the same noise whichever process it lands on; without it backbones use the global RNG."""
