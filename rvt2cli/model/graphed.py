"""A policy step as one CUDA graph: every kernel of both stages (renders included) launched by a
single replay, which removes the ~2 ms of Python and launch gaps an eager step spends on a fast GPU.

The graph is captured for one cloud size; clouds are padded to it with zero rows (the renderer and the
point counts ignore padding through `num_points`, as in a batch of clouds of several sizes). Replays read
the static input buffers and overwrite the static outputs.
"""

import torch

from rvt2cli.model.policy import Observation, Prediction, RVT2Policy


class GraphedPredictor:
    def __init__(self, policy: RVT2Policy, max_points: int, autocast: bool = True, warmup: int = 3):
        device = next(policy.parameters()).device
        if device.type != "cuda":
            raise ValueError("CUDA graphs need the policy on a CUDA device")
        cfg = policy.cfg
        self.policy, self.autocast, self.max_points = policy, autocast, max_points
        self.inputs = Observation(
            points=torch.zeros(1, max_points, 3, device=device), rgb=torch.zeros(1, max_points, 3, device=device),
            num_points=torch.ones(1, dtype=torch.long, device=device), proprio=torch.zeros(1, cfg.proprio_dim, device=device),
            lang=torch.zeros(1, cfg.lang_tokens, cfg.lang_dim, device=device),
            aim=torch.zeros(1, 3, device=device),  # zeros: the TCP itself
        )
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):  # warm up: kernels load, caches fill, allocations settle
            for _ in range(warmup):
                self._step()
        torch.cuda.current_stream(device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = self._step()

    def _step(self) -> tuple[torch.Tensor, ...]:
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=self.autocast):
            pred = self.policy.predict(self.inputs)
        return (pred.position, pred.rot_bins, pred.quaternion, pred.gripper_open, pred.ignore_collisions,
                pred.stage1_position)

    def predict(self, obs: Observation) -> Prediction:
        """`RVT2Policy.predict` of one observation of at most max_points points, by one replay (no stage outputs)."""
        n = obs.points.shape[1]
        if obs.points.shape[0] != 1 or n > self.max_points:
            raise ValueError(f"captured for 1 cloud of at most {self.max_points} points, got {tuple(obs.points.shape)}")
        self.inputs.points[:, :n].copy_(obs.points)
        self.inputs.points[:, n:].zero_()
        self.inputs.rgb[:, :n].copy_(obs.rgb)
        self.inputs.rgb[:, n:].zero_()
        self.inputs.num_points.copy_(obs.num_points)
        self.inputs.proprio.copy_(obs.proprio)
        self.inputs.lang.copy_(obs.lang)
        if obs.aim is None:  # an aim of zeros moves nothing: the TCP's position is the heatmaps' point
            self.inputs.aim.zero_()
        else:
            self.inputs.aim.copy_(obs.aim)
        self.graph.replay()
        position, rot_bins, quaternion, gripper_open, ignore_collisions, stage1 = (o.clone() for o in self.outputs)
        return Prediction(position=position, rot_bins=rot_bins, quaternion=quaternion, gripper_open=gripper_open,
                          ignore_collisions=ignore_collisions, stage1_position=stage1, stages=[])

    def __call__(self, obs: Observation) -> tuple[torch.Tensor, ...]:
        """obs with batch 1 and at most max_points points -> (position, rot_bins, gripper_open, ignore_collisions)."""
        pred = self.predict(obs)
        return pred.position, pred.rot_bins, pred.gripper_open, pred.ignore_collisions


class GraphedPolicy:
    """A policy whose `predict` of one observation replays a CUDA graph (`rvt2 eval --cuda-graph`: each worker asks
    for one keyframe at a time), answering what the policy's eager `predict` answers. The graph is captured at
    the first call, for that cloud's size rounded up, and again, larger, when a cloud outgrows it."""

    ROUND_POINTS = 16_384

    def __init__(self, policy: RVT2Policy, autocast: bool = False):
        self.policy, self.cfg, self.autocast = policy, policy.cfg, autocast
        self.predictor: GraphedPredictor | None = None

    def predict(self, obs: Observation) -> Prediction:
        if self.predictor is None or obs.points.shape[1] > self.predictor.max_points:
            self.predictor = None  # the old graph's memory goes back before the larger one is captured
            size = -(-obs.points.shape[1] // self.ROUND_POINTS) * self.ROUND_POINTS
            self.predictor = GraphedPredictor(self.policy, size, autocast=self.autocast)
        return self.predictor.predict(obs)
