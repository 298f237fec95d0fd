"""rvt2_client: call a policy served by `rvt2 serve` from a robot program (Python 3.10 and later).

    from rvt2_client import PolicyClient

    with PolicyClient("ws://gpu-box:8765", token=open("policy.token").read().strip()) as policy:
        keyframe = policy.predict({"front": {"rgb": rgb, "depth": depth_mm, "intrinsic": K, "cam2world": pose}},
                                  "put the block on the plate", gripper_open=True, finger_positions=(0.04, 0.04),
                                  keyframes_done=0, task="stack_blocks")
        keyframe.position, keyframe.quaternion, keyframe.gripper_open, keyframe.ignore_collisions

It needs numpy, msgpack and websockets (`pip install ./rvt2_client` from the rvt2 repository); the wire
format is in `rvt2_client.wire`, the robot-side loop in rvt2's docs/REAL_ROBOT.md ("Serving").
"""

from rvt2_client.wire import DEFAULT_PORT, PROTOCOL

__all__ = ["DEFAULT_PORT", "PROTOCOL", "Keyframe", "PolicyClient", "PolicyError"]
__version__ = "0.1.0"


def __getattr__(name):
    """The client's names, imported on first use: the wire format alone (`rvt2 serve`'s defaults) needs no websockets."""
    if name in ("Keyframe", "PolicyClient", "PolicyError"):
        from rvt2_client import client

        return getattr(client, name)
    raise AttributeError(f"module 'rvt2_client' has no attribute {name!r}")
