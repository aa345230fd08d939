"""Our environments in Gymnasium, and our study data as Minari datasets.

Importing this package registers the eleven environments with Gymnasium under the ``BAMStudy``
namespace (``BAMStudy/Doorway-v0``, ...). Gymnasium 1.x no longer loads plugins from entry
points, so a program that does not import us names the module in the id instead::

    import gymnasium
    env = gymnasium.make("server.rl:BAMStudy/Doorway-v0")
"""

from __future__ import annotations

from server.rl.environments import (
    ENVIRONMENT_IDS,
    NAMESPACE,
    BAMStudyEnv,
    environment_id,
    register_environments,
    step_reward,
)

register_environments()

__all__ = [
    "ENVIRONMENT_IDS",
    "NAMESPACE",
    "BAMStudyEnv",
    "environment_id",
    "register_environments",
    "step_reward",
]
