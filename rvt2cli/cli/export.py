"""`rvt2 export`: a deployable, parity-checked policy (ONNX or TorchScript)."""

from rvt2cli.cli.args import NON_NEGATIVE, integer


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="export a checkpoint as a self-contained ONNX or TorchScript policy",
        description="Export the whole policy step (rendering, both stages, 3D argmax, rotation) as one ONNX or "
                    "TorchScript model with a manifest and the training instructions' embeddings; the export is "
                    "compared with the PyTorch policy on recorded observations before it is kept.",
    )
    p.add_argument("--checkpoint", required=True, help="run folder or checkpoint written by `rvt2 train`")
    p.add_argument("--format", default="onnx", choices=["onnx", "torchscript"])
    p.add_argument("--out", default="policy", help="output folder (default policy/); an existing one must be a previous export")
    p.add_argument("--max-points", type=integer(16, 2**31 - 2), default=50_000, help="cloud size the model takes (pad smaller clouds)")
    p.add_argument("--check-data", nargs="+", metavar="PATH", help="episodes for the parity check (default: the run's own)")
    p.add_argument("--stage2-min-points", type=NON_NEGATIVE, metavar="N",
                   help="keep stage 1's point where fewer than N cloud points lie in stage 2's box, in the export "
                        "(default: the checkpoint's; match it to your cameras' clouds, docs/REAL_ROBOT.md)")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.export.exporter import export_policy

    report = export_policy(args.checkpoint, args.format, args.out, args.max_points, tuple(args.check_data or ()),
                           stage2_min_points=args.stage2_min_points)
    print(f"exported {args.format} policy to {args.out}/ (parity on {report.samples} observations: position within "
          f"{report.max_position_error_m * 1000:.3f} mm, same rotation bins and gripper)")
    return 0
