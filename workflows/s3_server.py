"""A real S3 API server on 127.0.0.1 for tests and benchmarks: moto's standalone server as a child
process (no mock of the client), and a TCP proxy in front of it that delays every request, to see
what a store's reads cost at a given round-trip latency."""

import contextlib
import importlib.util
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, Iterator

from .process_cluster import wait_for

CREDENTIALS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}


class ServerUnavailable(RuntimeError):
    """The S3 server cannot run here (a package missing, or it did not start): the reason."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _answers(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def client(endpoint: str):
    """A boto3 S3 client of ``endpoint`` with the test credentials."""
    import boto3
    return boto3.client("s3", endpoint_url=endpoint, region_name=CREDENTIALS["AWS_DEFAULT_REGION"],
                        aws_access_key_id=CREDENTIALS["AWS_ACCESS_KEY_ID"],
                        aws_secret_access_key=CREDENTIALS["AWS_SECRET_ACCESS_KEY"])


@contextlib.contextmanager
def moto_server(buckets=("maps",), timeout: float = 60.0) -> Iterator[str]:
    """Start moto's S3 server on a free port of 127.0.0.1 with ``buckets`` created; yields its
    endpoint URL and stops it after. ServerUnavailable says why it cannot start."""
    for module in ("moto", "s3fs", "boto3", "flask_cors"):
        if importlib.util.find_spec(module) is None:
            raise ServerUnavailable(f"the S3 server needs {module} (pip install -e '.[test]')")
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "moto.log"
        with open(log, "w") as out:
            server = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                                      stdout=out, stderr=subprocess.STDOUT)
        try:
            try:
                wait_for(lambda: _answers(port) or server.poll() is not None, timeout)
            except TimeoutError:
                pass
            if not _answers(port):
                raise ServerUnavailable(f"moto's S3 server did not start: {log.read_text()[-500:]}")
            endpoint = f"http://127.0.0.1:{port}"
            for bucket in buckets:
                client(endpoint).create_bucket(Bucket=bucket)
            yield endpoint
        finally:
            server.terminate()
            server.wait(30)


class DelayingProxy:
    """A TCP proxy on 127.0.0.1 in front of ``target_port`` that holds every request (each chunk
    a client sends) ``delay`` seconds before passing it on: one round trip of that latency per
    request. Counts the requests (by HTTP method) and the bytes that come back."""

    def __init__(self, target_port: int, delay: float):
        self.target_port, self.delay = target_port, delay
        self.requests: Dict[str, int] = {}
        self.bytes_back = 0
        self._lock = threading.Lock()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self._closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def reset(self) -> None:
        with self._lock:
            self.requests, self.bytes_back = {}, 0

    def _accept(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.target_port))
            threading.Thread(target=self._pump, args=(conn, upstream, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, conn, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, requests: bool) -> None:
        try:
            while True:
                data = src.recv(1 << 16)
                if not data:
                    break
                if requests:
                    method = data.split(b" ", 1)[0].decode(errors="replace")
                    if method.isalpha() and method.isupper():  # a request starts here (not a body's chunk)
                        with self._lock:
                            self.requests[method] = self.requests.get(method, 0) + 1
                        time.sleep(self.delay)
                else:
                    with self._lock:
                        self.bytes_back += len(data)
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        self._closed = True
        self._listener.close()


def port_of(endpoint: str) -> int:
    return int(endpoint.rsplit(":", 1)[1])

