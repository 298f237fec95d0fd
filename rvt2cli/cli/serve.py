"""`rvt2 serve`: the policy as a network service that robots call (websockets, msgpack; docs/SERVING.md)."""

from rvt2cli.cli.args import COUNT, NON_NEGATIVE, integer, names, number


def register(subparsers) -> None:
    from rvt2_client.wire import DEFAULT_PORT, MAX_MESSAGE_BYTES
    from rvt2cli.serve.options import ServeOptions as S

    p = subparsers.add_parser(
        "serve", help="serve a policy to robots over the network (websockets + msgpack; client: rvt2_client)",
        description="Answer `predict` requests (camera frames or a fused cloud, the instruction and the gripper's state -> "
                    "the next keyframe) from robots over a websocket, with rvt2_client.PolicyClient (numpy, msgpack and "
                    "websockets alone, Python 3.10+). Requests that arrive together share one forward pass. GET /healthz on "
                    "the same port describes the model (its sha256, config, device). One log line per request on stderr; "
                    "SIGTERM or Ctrl-C stops after answering the requests in flight. Protocol and operations: docs/SERVING.md.",
    )
    p.add_argument("--checkpoint", required=True, metavar="RUN|EXPORT",
                   help="run folder or checkpoint written by `rvt2 train`, or a folder written by `rvt2 export`")
    p.add_argument("--host", default=S.host, help=f"address to listen on (default {S.host}, this machine only; any other "
                                                   "needs --token-file)")
    p.add_argument("--port", type=integer(0, 65535), default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0: a free one, printed)")
    p.add_argument("--device", default="cpu", help="the policy's device (default cpu; cuda, cuda:1, ...)")
    p.add_argument("--token-file", metavar="FILE",
                   help="a file holding the shared secret every request must carry (compared in constant time); "
                        "required off the loopback. Make one: python -c 'import secrets; print(secrets.token_urlsafe(32))' > FILE")
    p.add_argument("--max-batch", type=COUNT, default=S.max_batch, help=f"requests answered in one forward pass at most (default {S.max_batch})")
    p.add_argument("--fixed-batch", action="store_true",
                   help="run every forward pass at --max-batch, padded with copies: a request's answer then does not depend "
                        "on how many others arrived with it (on a GPU, whose kernels depend on the batch's shape); costs "
                        "a full batch's compute per pass")
    p.add_argument("--max-wait-ms", type=number(0.0, 1000.0), default=S.max_wait_ms,
                   help=f"how long a request waits for others to share its forward pass (default {S.max_wait_ms:g} ms)")
    p.add_argument("--max-message-mb", type=number(0.001, 4096.0), default=MAX_MESSAGE_BYTES / 2**20,
                   help=f"the largest request, MiB (default {MAX_MESSAGE_BYTES / 2**20:g}); larger ones are refused")
    p.add_argument("--cameras", type=names, metavar="A,B",
                   help="camera names every request's frames must include (default: any cameras)")
    p.add_argument("--stage2-min-points", type=NON_NEGATIVE, metavar="N",
                   help="a checkpoint's stage-2 point minimum, as rvt2 eval and rvt2 export take it (default: the checkpoint's)")
    p.set_defaults(run=run)


def run(args) -> int:
    import logging
    import sys
    import warnings

    from rvt2cli.serve.options import ServeOptions, token_from_file
    from rvt2cli.serve.server import open_server

    warnings.simplefilter("default")
    token = token_from_file(args.token_file) if args.token_file else None
    if args.token_file:
        import os
        import stat

        if os.stat(args.token_file).st_mode & (stat.S_IRGRP | stat.S_IROTH):
            warnings.warn(f"{args.token_file} is readable by other users of this machine; `chmod 600 {args.token_file}`")
    handler = logging.StreamHandler(sys.stderr)   # one line per request; other libraries' logs stay quiet
    handler.setFormatter(logging.Formatter("%(asctime)s rvt2 serve: %(message)s"))
    log = logging.getLogger("rvt2.serve")
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False
    options = ServeOptions(host=args.host, port=args.port, token=token, max_batch=args.max_batch, max_wait_ms=args.max_wait_ms,
                           fixed_batch=args.fixed_batch, max_message_bytes=int(args.max_message_mb * 2**20), cameras=tuple(args.cameras or ()))
    server = open_server(args.checkpoint, args.device, options, args.stage2_min_points)
    model = server.model

    def ready(url: str) -> None:
        http = "http" + url[2:]
        print(f"serving {model['kind']} {model['path']} (sha256 {model['sha256'][:16]}..., {server.policy.device}) on {url}; "
              f"health: {http}/healthz; SIGTERM or Ctrl-C stops", flush=True)

    server.serve_forever(on_ready=ready)
    return 0
