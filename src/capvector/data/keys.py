"""The batch keys as constants, for code written against them (backbones of other packages, the
tests). capvector's own code indexes ``capvector.data.batch.Batch`` with its literal keys, where
the keys, shapes and dtypes are declared; ``tests/test_batch.py`` checks these name the same keys.
"""

from typing import Final

IMAGES: Final = "images"
PROPRIO: Final = "proprio"
ACTIONS: Final = "actions"
INSTRUCTION: Final = "instruction"
DEPTH: Final = "depth"
INTRINSICS: Final = "intrinsics"
ANNOTATION: Final = "annotation"
INDEX: Final = "index"
NOISE_SEED: Final = "noise_seed"
