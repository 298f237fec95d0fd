"""Serving a policy to robots over the network (`rvt2 serve`).

    batching.py   Batcher: requests that arrive together answered by one call, each with its own answer
    requests.py   a predict request checked field by field into the policy's input
    server.py     PolicyServer: websockets + msgpack (rvt2_client.wire), health, logs, graceful stop

    from rvt2cli.serve.options import ServeOptions
    from rvt2cli.serve.server import open_server

    server = open_server("runs/multi", device="cuda", options=ServeOptions(host="0.0.0.0", token=token))
    server.serve_forever(on_ready=print)          # or server.start_in_thread().url

Robots call it with `rvt2_client.PolicyClient` (numpy, msgpack and websockets alone).
"""
