"""snac-jax: the SNAC mobile-construction benchmark as pure-functional JAX environments."""

from snac_jax.config import EnvConfig
from snac_jax.env import SNACEnv
from snac_jax.metrics import grid_iou, iou
from snac_jax.state import EnvParams, EnvState
from snac_jax.tasks import OVERRIDES, TASKS, make, test_design_names

__all__ = [
    "EnvConfig",
    "EnvParams",
    "EnvState",
    "OVERRIDES",
    "SNACEnv",
    "TASKS",
    "grid_iou",
    "iou",
    "make",
    "test_design_names",
]
__version__ = "0.1.0"
