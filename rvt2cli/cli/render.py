"""`rvt2 render EPISODE --frame N`: the virtual views the network sees, as PNG (and the cloud as PLY)."""

from rvt2cli.cli.args import NON_NEGATIVE, integer


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="render the network's virtual views of an episode frame (PNG, contact sheet, PLY)",
        description="Render the fused cloud of one frame with the point renderer into the RVT-2 virtual views "
                    "(top, front, right; --rig rvt1 for five), optionally zoomed 4x around a point as stage 2 "
                    "does, and, with --checkpoint, the policy's predicted heatmaps over both stages' views.",
    )
    p.add_argument("episode", help="episode .mcap file")
    p.add_argument("--frame", type=NON_NEGATIVE, required=True, help="a frame with observations (see `rvt2 info`)")
    p.add_argument("--out", default="views", help="output folder (default views/)")
    p.add_argument("--zoom-at", help="also render the stage-2 views zoomed around next-keyframe or X,Y,Z (m, world)")
    p.add_argument("--ply", action="store_true", help="also write the fused cloud as PLY")
    p.add_argument("--checkpoint", help="overlay this policy's predicted heatmaps")
    p.add_argument("--rig", choices=["rvt2", "rvt1"], default="rvt2", help="three views (RVT-2) or five (RVT-1)")
    p.add_argument("--image-size", type=integer(8, 2048), default=224, help="pixels per side (default 224)")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.render.snapshot import render_frame

    overlay = None
    if args.checkpoint:
        from rvt2cli.eval.heatmaps import heatmap_overlay

        overlay = heatmap_overlay(args.checkpoint)
    written = render_frame(args.episode, args.frame, args.out, zoom_at=args.zoom_at, ply=args.ply, overlay=overlay,
                           image_size=args.image_size, rig=args.rig)
    sheet = next(p for p in written if p.name.endswith("_sheet.png"))
    print(f"wrote {len(written)} files to {args.out}/; contact sheet: {sheet}")
    return 0
