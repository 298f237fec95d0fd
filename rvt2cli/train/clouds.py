"""Where the packed training clouds live (`rvt2 train --samples-on`), and how a batch's rows reach the GPU.

The clouds are nearly all of the training data: at 50,000 points a sample takes 750 KB (xyz float32, rgb
uint8), so rvt2-18's 62,502 samples take 43.7 GiB. On the GPU (`device`), a batch is an index into them
there, which leaves a 24 or 40 GB card too little for the network, and four times the demos would not fit
an H200. On the host (`host`), they stay in ordinary memory and each batch's rows travel on their own:
gathered on the host into a pinned staging buffer (one `index_select` per tensor, no loop over samples),
then copied without blocking on a side stream that the training stream waits for. The loop makes a batch
while the GPU still runs the step before it, so that copy (144 MB at batch 192, a few milliseconds over
PCIe) runs beside that step rather than before the next. The rows are the same bytes either way, so the
batches are the same: only where they are read from changes.

`auto` (the default) keeps the clouds on the GPU where they take at most `DEVICE_SHARE` of its free memory
(every run did so before, and rvt2-18 on an H200 still does), else on the host.
"""

import numpy as np
import torch

SAMPLES_ON = ("auto", "host", "device")
DEVICE_SHARE = 0.5   # `auto`: the clouds' largest share of the GPU's free memory at loading; the rest is the network's


def clouds_bytes(samples: int, max_points: int) -> int:
    """What `samples` packed clouds take: xyz float32 and rgb uint8, `max_points` rows each."""
    return samples * max_points * (3 * 4 + 3)


def clouds_on_host(samples_on: str, nbytes: int, device: torch.device) -> bool:
    """The one decision of where the clouds live: on the host (True) or on `device`. On a CPU both are host
    memory, but `host` still takes the host's path (rows gathered, then moved), so that path runs there too."""
    if samples_on not in SAMPLES_ON:
        raise ValueError(f"samples_on must be one of {SAMPLES_ON}, not {samples_on!r}")
    if samples_on != "auto":
        return samples_on == "host"
    if device.type != "cuda":
        return False
    free, _ = torch.cuda.mem_get_info(device)
    return nbytes > DEVICE_SHARE * free


def host_rows(xyz: torch.Tensor, rgb: torch.Tensor, idx: np.ndarray, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The host-resident clouds of samples `idx` on `device`, through freshly pinned memory (validation and
    one-off batches; the training loop's batches go through `StagedRows`)."""
    rows = torch.from_numpy(np.asarray(idx, np.int64))
    picked = torch.index_select(xyz, 0, rows), torch.index_select(rgb, 0, rows)
    if device.type != "cuda":
        return picked
    return tuple(t.pin_memory().to(device, non_blocking=True) for t in picked)


class StagedRows:
    """The training loop's way to the GPU for host-resident clouds: each call gathers a batch's rows into one
    of two pinned staging buffers and copies them on a side stream; the current stream waits for that copy
    (on the GPU, not the host), and the buffer is written again only once its last copy is done (two calls
    later, so the host never waits for the step that is running)."""

    BUFFERS = 2

    def __init__(self, xyz: torch.Tensor, rgb: torch.Tensor, device: torch.device, rows: int):
        self.xyz, self.rgb, self.device = xyz, rgb, device
        self.cuda = device.type == "cuda"
        self.stream = torch.cuda.Stream(device) if self.cuda else None
        self.buffers = [self._buffers(rows) for _ in range(self.BUFFERS)] if self.cuda else []
        self.copied = [None] * self.BUFFERS   # each buffer's last copy (a CUDA event)
        self.turn = 0

    def _buffers(self, rows: int) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.empty((rows, *self.xyz.shape[1:]), dtype=self.xyz.dtype, pin_memory=True),
                torch.empty((rows, *self.rgb.shape[1:]), dtype=self.rgb.dtype, pin_memory=True))

    def __call__(self, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """The clouds' `rows` on the device (rows of `xyz` and `rgb`: sample indices, or a shard's rows)."""
        if not self.cuda:
            return host_rows(self.xyz, self.rgb, rows, self.device)
        turn, self.turn = self.turn, (self.turn + 1) % self.BUFFERS
        if self.copied[turn] is not None:
            self.copied[turn].synchronize()
        n = len(rows)
        if n > len(self.buffers[turn][0]):  # more rows than ever before (a shard serving many processes)
            self.buffers[turn] = self._buffers(n)
        xyz_buffer, rgb_buffer = (b[:n] for b in self.buffers[turn])
        index = torch.from_numpy(np.asarray(rows, np.int64))
        torch.index_select(self.xyz, 0, index, out=xyz_buffer)
        torch.index_select(self.rgb, 0, index, out=rgb_buffer)
        with torch.cuda.stream(self.stream):
            xyz = xyz_buffer.to(self.device, non_blocking=True)
            rgb = rgb_buffer.to(self.device, non_blocking=True)
            self.copied[turn] = self.stream.record_event()
        current = torch.cuda.current_stream(self.device)
        current.wait_stream(self.stream)
        for tensor in (xyz, rgb):  # made on the side stream, used on this one: not reused before this one is done
            tensor.record_stream(current)
        return xyz, rgb

    def pinned_bytes(self) -> int:
        return sum(t.nbytes for pair in self.buffers for t in pair)
