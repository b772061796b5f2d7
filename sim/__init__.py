"""indoorbev_sim: MuJoCo/MJX scenes, Warp lidar ray casting and labelled frames.

Import-light: the names below load their modules on first use, so ``import indoorbev_sim``
pulls in neither Warp nor MuJoCo.

    from indoorbev_sim import generate_batch
    batch = jax.jit(generate_batch, static_argnums=(1, 2))(key, Config.small())
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "generate_batch": "indoorbev_sim.generate",
    "generate_batch_with_info": "indoorbev_sim.generate",
    "generate_sequences": "indoorbev_sim.generate",
    "FrameInfo": "indoorbev_sim.generate",
    "sample_scenes": "indoorbev_sim.generate",
    "write_rosbag": "indoorbev_sim.export",
    "read_rosbag": "indoorbev_sim.export",
    "render_frame": "indoorbev_sim.show",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'indoorbev_sim' has no attribute {name!r}")
