"""`rvt2 serve`: one policy answering robots over websockets (msgpack messages, `rvt2_client.wire`).

    connection (one per robot) --message--> check size, decode, token --> check the fields and fuse the
    cameras (a thread pool) --> Batcher (requests that arrive together share one forward pass) --> reply

Every request is answered, or refused with the field that was wrong; only bytes that are not a msgpack map
close their connection. Each request is logged in one line with its latency. GET /healthz on the same port
describes the server. SIGTERM (or Ctrl-C) stops it gracefully: no new connections, new requests refused
("server": shutting down), those in flight answered, then the connections closed.
"""

import asyncio
import hashlib
import hmac
import json
import logging
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from pathlib import Path

from websockets.asyncio.server import serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode

from rvt2_client.wire import HEALTH_PATH, PROTOCOL, WireError, pack, unpack
from rvt2cli import __version__
from rvt2cli.deploy import KeyframePolicy, PolicyInput
from rvt2cli.errors import UserError
from rvt2cli.runtime import torch_device
from rvt2cli.serve.batching import Batcher, at_fixed_size
from rvt2cli.serve.options import ServeOptions, is_loopback
from rvt2cli.serve.requests import MAX_INSTRUCTION_CHARS, predict_inputs

log = logging.getLogger("rvt2.serve")


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(2**22), b""):
            digest.update(block)
    return digest.hexdigest()


def gpu_memory(device) -> dict:
    """This process's memory on the policy's GPU, MiB: what PyTorch holds now, the most it held, what it reserved."""
    import torch

    return {"allocated": round(torch.cuda.memory_allocated(device) / 2**20),
            "peak_allocated": round(torch.cuda.max_memory_allocated(device) / 2**20),
            "reserved": round(torch.cuda.memory_reserved(device) / 2**20)}


class PolicyServer:
    def __init__(self, policy: KeyframePolicy, options: ServeOptions = ServeOptions()):
        self.policy, self.options = policy, options
        self.model = policy.describe()
        self.model["sha256"] = file_sha256(Path(self.model["weights"]))
        # a fixed batch: what a request is answered does not depend on how many arrived with it (batching.at_fixed_size)
        self.forward = at_fixed_size(policy.predict_inputs, options.max_batch) if options.fixed_batch else policy.predict_inputs
        self.batcher = Batcher(self.forward, options.max_batch, options.max_wait_ms / 1000, name="rvt2-serve-batcher")
        self.prepare = ThreadPoolExecutor(options.prepare_threads, thread_name_prefix="rvt2-serve-prepare")
        self.started = time.time()
        self.counts = {"answered": 0, "refused": 0}
        self.in_flight = 0
        self.draining = False
        self._idle: asyncio.Event | None = None

    # --- what it serves ----------------------------------------------------------------------------------
    def info(self) -> dict:
        """The health document: the model and its checkpoint's sha256, config, device, tasks, limits, counts."""
        o = self.options
        return {"status": "draining" if self.draining else "ok", "protocol": PROTOCOL, "rvt2_version": __version__,
                "model": {k: self.model[k] for k in ("kind", "path", "weights", "sha256", "step") if k in self.model},
                "config": self.model["config"], "device": str(self.policy.device), "rigs": self.model.get("rigs", {}),
                "phrasings": self.model.get("phrasings"),
                "tasks": {t: {"scene_bounds": b, "aim_offset": self.policy.aim_offsets.get(t)} for t, b in self.policy.tasks.items()},
                "cameras": list(o.cameras), "max_message_bytes": o.max_message_bytes,
                "max_instruction_chars": MAX_INSTRUCTION_CHARS,
                "batching": {"max_batch": o.max_batch, "max_wait_ms": o.max_wait_ms, "fixed_batch": o.fixed_batch,
                             "requests": self.batcher.stats.requests,
                             "batches": self.batcher.stats.batches, "largest": self.batcher.stats.largest},
                "requests": dict(self.counts), "uptime_s": round(time.time() - self.started, 1),
                **({"gpu_memory_mib": gpu_memory(self.policy.device)} if str(self.policy.device).startswith("cuda") else {})}

    def warm_up(self) -> None:
        """One forward pass before the first robot's (kernels compiled, memory taken)."""
        import numpy as np
        import torch

        from rvt2cli.data.episode import Cloud
        from rvt2cli.model.observation import LANG_DIM

        task, bounds = next(iter(self.policy.tasks.items()))
        lo, hi = np.asarray(bounds[:3], np.float32), np.asarray(bounds[3:], np.float32)
        xyz = np.random.default_rng(0).uniform(lo, hi, size=(1000, 3)).astype(np.float32)
        cloud = Cloud(xyz=xyz, rgb=np.full((1000, 3), 128, np.uint8))
        lang = torch.zeros(self.policy.instructions.tokens, LANG_DIM)
        self.forward([PolicyInput(cloud, True, np.array([0.04, 0.04], np.float32), 0, lang, list(bounds), None)])

    # --- one connection --------------------------------------------------------------------------------
    def _authorised(self, given) -> bool:
        token = self.options.token
        if token is None:
            return True
        return isinstance(given, str) and hmac.compare_digest(given.encode(), token.encode())

    async def _connection(self, connection) -> None:
        peer = "%s:%s" % connection.remote_address[:2] if connection.remote_address else "?"
        try:
            async for data in connection:
                start = time.perf_counter()
                self.in_flight += 1
                try:
                    reply, line, close = await self._answer(data)
                    self.counts["answered" if reply.get("ok") else "refused"] += 1
                    try:
                        await connection.send(pack(reply))
                    except ConnectionClosed:
                        line += " (the client left before its answer)"
                        close = False
                finally:
                    self.in_flight -= 1
                    if self.in_flight == 0 and self._idle is not None:
                        self._idle.set()
                log.info("%s %s latency_ms=%.1f", peer, line, (time.perf_counter() - start) * 1000)
                if close:
                    await connection.close(CloseCode.INVALID_DATA, "not an rvt2 message")
                    return
        except ConnectionClosed as e:  # the client went away mid-message, or its frames broke the protocol
            if e.rcvd is None or e.rcvd.code not in (CloseCode.NORMAL_CLOSURE, CloseCode.GOING_AWAY):
                log.info("%s connection lost: %s", peer, e)

    async def _answer(self, data) -> tuple[dict, str, bool]:
        """(the reply, its log line, whether to close the connection after it)."""
        def refuse(request_id, field_name: str, error: str, close: bool = False):
            return ({"id": request_id, "ok": False, "field": field_name, "error": error},
                    f"id={request_id} status=refused field={field_name} error={error[:160]!r}", close)

        if len(data) > self.options.max_message_bytes:
            return refuse(None, "message", f"{len(data) / 2**20:.1f} MiB, over the server's limit of "
                                           f"{self.options.max_message_bytes / 2**20:.1f} MiB (rvt2 serve --max-message-mb)")
        try:
            message = unpack(data)
        except ValueError as e:
            return refuse(None, "message", f"{e}; this server speaks rvt2_client's msgpack messages", close=True)
        request_id = message.get("id")
        if request_id is not None and (not isinstance(request_id, int) or isinstance(request_id, bool)):
            return refuse(None, "id", f"not a whole number (got {request_id!r:.40})")
        if not self._authorised(message.get("token")):
            return refuse(request_id, "token", "missing" if message.get("token") is None else "wrong token")
        kind = message.get("type")
        if self.draining:
            return refuse(request_id, "server", "shutting down; send the request again once it is back")
        if kind == "info":
            return {"id": request_id, "ok": True, "info": self.info()}, f"id={request_id} type=info status=ok", False
        if kind != "predict":
            return refuse(request_id, "type", f"{kind!r:.40} is not a request this server answers (info, predict)")
        try:
            inputs = await asyncio.get_running_loop().run_in_executor(self.prepare, predict_inputs, message, self.policy,
                                                                       self.options.cameras)
            future = self.batcher.submit(inputs)
            keyframe = await asyncio.wrap_future(future)
        except WireError as e:
            return refuse(request_id, e.field, e.message)
        except Exception as e:  # noqa: BLE001 - one request's failure is its own; the server goes on
            log.exception("request %s failed", request_id)
            return refuse(request_id, "server", f"{type(e).__name__}: {e}")
        reply = {"id": request_id, "ok": True, "batch": future.batch_size,
                 "keyframe": {"tcp_pose": list(keyframe.position + keyframe.quaternion), "gripper_open": keyframe.gripper_open,
                              "ignore_collisions": keyframe.ignore_collisions}}
        return reply, (f"id={request_id} type=predict status=ok task={message.get('task')} "
                       f"points={len(inputs.cloud)} batch={future.batch_size}"), False

    def _http(self, connection, request):
        """GET /healthz: the health document as JSON (with the token, as `Authorization: Bearer TOKEN`, where
        the server has one). Other paths go on to the websocket handshake."""
        if request.path.split("?")[0] != HEALTH_PATH:
            return None
        given = request.headers.get("Authorization", "")
        if not self._authorised(given[len("Bearer "):] if given.startswith("Bearer ") else None):
            log.info("%s GET %s status=401", connection.remote_address[0] if connection.remote_address else "?", HEALTH_PATH)
            return connection.respond(HTTPStatus.UNAUTHORIZED, "send the token as 'Authorization: Bearer TOKEN'\n")
        response = connection.respond(HTTPStatus.OK, json.dumps(self.info(), indent=1) + "\n")
        response.headers["Content-Type"] = "application/json"
        log.info("%s GET %s status=200", connection.remote_address[0] if connection.remote_address else "?", HEALTH_PATH)
        return response

    # --- the whole server ------------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event, on_ready=None) -> None:
        """Serve until `stop` is set, then stop gracefully. `on_ready(url)` once listening."""
        o = self.options
        self._idle = asyncio.Event()
        self._idle.set()
        async with serve(self._connection, o.host, o.port, process_request=self._http, compression=None,
                         max_size=2 * o.max_message_bytes, server_header=f"rvt2/{__version__}") as server:
            host, port = server.sockets[0].getsockname()[:2]
            if on_ready:
                on_ready(f"ws://{f'[{host}]' if ':' in host else host}:{port}")
            await stop.wait()
            server.server.close()   # no new connections
            self.draining = True     # new requests on open ones are refused
            if self.in_flight:
                self._idle.clear()
                log.info("stopping: answering the %d requests in flight", self.in_flight)
                await self._idle.wait()
        self.batcher.close()
        self.prepare.shutdown()
        log.info("stopped after %d answers and %d refusals", self.counts["answered"], self.counts["refused"])

    def serve_forever(self, on_ready=None) -> None:
        """Serve in this (the main) thread until SIGTERM or SIGINT."""
        async def main():
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, stop.set)
            await self.run(stop, on_ready)

        asyncio.run(main())

    def start_in_thread(self) -> "ServerThread":
        """Serve from a background thread of this process (the evaluation's shared policy, tests)."""
        return ServerThread(self)


class ServerThread:
    """A PolicyServer running in a thread: `url`, then `stop()` (graceful, as SIGTERM)."""

    def __init__(self, server: PolicyServer):
        self.server = server
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self.url: str | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="rvt2-serve", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self.error is not None:
            raise self.error

    def _main(self) -> None:
        async def main():
            self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()

            def ready(url):
                self.url = url
                self._ready.set()

            await self.server.run(self._stop, ready)

        try:
            asyncio.run(main())
        except BaseException as e:  # noqa: BLE001 - handed to the thread that started it
            self.error = e
            self._ready.set()

    def stop(self) -> None:
        if self._loop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join()


def open_server(checkpoint: str, device: str = "cpu", options: ServeOptions = ServeOptions(),
                stage2_min_points: int | None = None) -> PolicyServer:
    """The policy in `checkpoint` (a run, a checkpoint or an `rvt2 export` folder) loaded on `device`, warmed
    up, ready to serve with `options`. Refuses, in one line, an address off the loopback without a token."""
    if not is_loopback(options.host) and options.token is None:
        raise UserError(f"serving on {options.host} (off this machine's loopback) needs --token-file: a shared secret "
                        "every request must carry")
    if torch_device(device).type == "cuda":
        if (Path(checkpoint) / "manifest.json").is_file():
            raise UserError(f"{checkpoint}: an exported policy runs on the CPU (onnxruntime's CPU provider or TorchScript "
                            "on the CPU); serve the checkpoint it was exported from for --device cuda")
    server = PolicyServer(KeyframePolicy.load(checkpoint, device, stage2_min_points), options)
    server.warm_up()
    return server
