"""Environments of the paper, registered with gymnasium on import.

``import envs`` then ``gymnasium.make("SimpleShapes-v0")`` or
``gymnasium.make_vec("SimpleShapes-v0", num_envs=N, vectorization_mode="vector_entry_point")``.
"""

import gymnasium

gymnasium.register(
    id="SimpleShapes-v0",
    entry_point="envs.simple_shapes:SimpleShapesEnv",
    vector_entry_point="envs.simple_shapes:SimpleShapesVectorEnv",
)

__all__ = ["simple_shapes"]
