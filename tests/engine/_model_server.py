"""A local HTTP server on 127.0.0.1 for the model-manager tests (no internet).

Routes serve bytes the test registers: ``full`` (honours Range), ``drop`` (the first
request without Range sends half the body then closes the connection), ``stall`` (sends
a little then goes silent), anything else 404.
"""

from __future__ import annotations

import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer


class ModelServer:
    """``with ModelServer() as srv: srv.add("/m.onnx", data); srv.url("/m.onnx")``."""

    def __init__(self):
        self.files: dict[str, tuple[bytes, str]] = {}
        self.requests: list[tuple[str, str | None]] = []  # (path, Range header)
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *_args):  # keep pytest output clean
                pass

            def do_GET(self):  # noqa: N802 (http.server API)
                rng = self.headers.get("Range")
                server.requests.append((self.path, rng))
                if self.path not in server.files:
                    self.send_error(404, "Not Found")
                    return
                data, mode = server.files[self.path]
                start = int(rng.split("=")[1].split("-")[0]) if rng and mode != "norange" else 0
                if mode == "drop" and not rng:
                    self._head(200, len(data))
                    self.wfile.write(data[: len(data) // 2])
                    self.wfile.flush()
                    self.close_connection = True
                    return
                if mode == "stall":
                    self._head(200, len(data))
                    self.wfile.write(data[:100])
                    self.wfile.flush()
                    time.sleep(3.0)
                    return
                if start:
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                    self.send_header("Content-Length", str(len(data) - start))
                    self.end_headers()
                else:
                    self._head(200, len(data))
                self.wfile.write(data[start:])

            def _head(self, code, length):
                self.send_response(code)
                self.send_header("Content-Length", str(length))
                self.end_headers()

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def add(self, path: str, data: bytes, mode: str = "full") -> str:
        self.files[path] = (data, mode)
        return self.url(path)

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}{path}"

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()


def tiny_onnx_bytes(n: int = 32, seed: int = 0) -> bytes:
    """A valid ONNX depth model (mean of RGB as relative inverse depth, [1,3,n,n] -> [1,1,n,n]).

    ``seed`` adds an unused initialiser so different seeds give different files (hashes).
    """
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    pad = np.random.default_rng(seed).standard_normal(4096).astype(np.float32)
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["img", "axes"], ["inv"], keepdims=1)], "depth",
        [helper.make_tensor_value_info("img", TensorProto.FLOAT, [1, 3, n, n])],
        [helper.make_tensor_value_info("inv", TensorProto.FLOAT, [1, 1, n, n])],
        [numpy_helper.from_array(np.array([1], np.int64), "axes"), numpy_helper.from_array(pad, "unused")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    return model.SerializeToString()
