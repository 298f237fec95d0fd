"""One-screen summaries of episode files (what `rvt2 info` prints)."""

from pathlib import Path

from rvt2cli.data.reader import read_episode


def summarize(path: str | Path) -> dict:
    ep = read_episode(path)
    return {
        "file": str(ep.path),
        "format_version": ep.format_version,
        "task": ep.meta.task,
        "instruction": ep.instruction["text"],
        "variation": ep.variation_index,
        "variation_values": dict(ep.instruction.get("variation", {})),
        "frames": ep.num_frames,
        "duration_s": round(ep.num_frames / ep.meta.control_hz, 3),
        "success": ep.meta.success,
        "seed": ep.meta.seed,
        "expert": ep.meta.expert,
        "cameras": list(ep.meta.cameras),
        "renderer": ep.meta.extra.get("renderer"),   # the Vulkan driver that drew them (None: not recorded by rvt2 record)
        "obs_frames": len(ep.meta.obs_frames),
        "keyframes": None if ep.keyframes is None else len(ep.keyframes.keyframes),
        "samples": None if ep.keyframes is None else len(ep.keyframes.samples),
        "channels": dict(sorted(ep.channel_counts.items())),
        "size_bytes": ep.size_bytes,
    }


def format_summary(s: dict) -> str:
    kf = "none (run `rvt2 extract-keyframes`)" if s["keyframes"] is None else f"{s['keyframes']} ({s['samples']} training samples)"
    lines = [
        f"{s['file']}",
        f"  task         {s['task']}  (seed {s['seed']}, expert {s['expert']})",
        f"  instruction  {s['instruction']!r}",
        f"  variation    {s['variation']}" + "".join(f"  {k}={v}" for k, v in sorted(s["variation_values"].items())),
        f"  frames       {s['frames']}  ({s['duration_s']:.2f} s), {s['obs_frames']} with observations",
        f"  success      {s['success']}",
        f"  cameras      {', '.join(s['cameras']) or 'none'}" + (f"  (rendered by {s['renderer']})" if s["renderer"] else ""),
        f"  keyframes    {kf}",
        f"  size         {s['size_bytes'] / 1e6:.2f} MB  (format {s['format_version']})",
        "  channels",
    ]
    width = max(len(t) for t in s["channels"])
    lines += [f"    {topic:<{width}}  {count:>5}" for topic, count in s["channels"].items()]
    return "\n".join(lines)
