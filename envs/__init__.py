"""Environments of the paper, registered with gymnasium on import.

``import envs`` then ``gymnasium.make("SimpleShapes-v0")``,
``gymnasium.make_vec("SimpleShapes-v0", num_envs=N, vectorization_mode="vector_entry_point")`` or
``gymnasium.make("RoboDesk-v0", task="push_green")``. Importing ``envs`` does not import mujoco.
"""

import gymnasium

gymnasium.register(
    id="SimpleShapes-v0",
    entry_point="envs.simple_shapes:SimpleShapesEnv",
    vector_entry_point="envs.simple_shapes:SimpleShapesVectorEnv",
)

gymnasium.register(
    id="RoboDesk-v0",
    entry_point="envs.robodesk:RoboDeskEnv",
)

__all__ = ["robodesk", "simple_shapes"]
