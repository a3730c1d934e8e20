"""Against a real `greyfit serve` on loopback: slow senders cannot lock out the other POSTs.

Defect: the in-flight body budget was reserved by the declared Content-Length and a body had no
deadline, so two connections declaring 64 MB bodies (the budget is 128 MB) and sending a byte a
second held all of it: every other POST answered 503 for as long as they kept sending. Now the
budget is charged by the bytes received, and a body not in within GREYFIT_BODY_READ_SECONDS is cut
with 408 (real sockets, real server)."""
import socket
import threading
import time

import httpx

from tests.servers import free_port, msd_request, start_server, stop_server

DECLARED = 64 * 1024 * 1024
READ_SECONDS = 4.0


def _recv_or_nothing(sock: socket.socket) -> bytes:
    try:
        return sock.recv(65536)
    except (socket.timeout, OSError):
        return b""


def slow_sender(port: int, stop: threading.Event, answers: list) -> None:
    """Declare a 64 MB body, then send one byte a second until answered (or stopped); keep the answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall((f"POST /v1/jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                      f"Content-Length: {DECLARED}\r\n\r\n").encode())
        sock.settimeout(1.0)
        sent, deadline = 0, time.monotonic() + 30
        while not stop.is_set() and time.monotonic() < deadline:
            try:
                answer = sock.recv(65536)
            except socket.timeout:
                answer = b""
            if answer:                                    # the rest of the answer, until the server closes
                while chunk := _recv_or_nothing(sock):
                    answer += chunk
                answers.append(answer.decode(errors="replace"))
                return
            try:
                sock.sendall(b" " if sent else b"{")
                sent += 1
            except OSError:
                answers.append("closed")
                return
        answers.append("no answer")


def test_two_slow_64_mb_senders_do_not_lock_out_a_small_fit(tmp_path):
    port = free_port()
    server = start_server(tmp_path, port, workers=1, GREYFIT_BODY_READ_SECONDS=str(READ_SECONDS))
    stop, answers = threading.Event(), [[], []]
    senders = [threading.Thread(target=slow_sender, args=(port, stop, answers[i])) for i in range(2)]
    try:
        for t in senders:
            t.start()
        time.sleep(1.5)                                   # both declared 64 MB and are trickling bytes
        base = f"http://127.0.0.1:{port}"
        resp = httpx.post(f"{base}/v1/fits", json=msd_request(0, n=41), timeout=60)
        assert resp.status_code == 200, resp.text          # the budget is not held by declared lengths
        assert abs(resp.json()["parameters"]["k"]["value"] - 5.0) < 0.25   # the truth simulated: k = 5
        for t in senders:
            t.join(timeout=30)
        for got in answers:                                # each slow sender was cut after the deadline
            assert got and got[0].startswith("HTTP/1.1 408"), got
            assert "GREYFIT_BODY_READ_SECONDS" in got[0]
        job = httpx.post(f"{base}/v1/jobs", json={"requests": [msd_request(1, n=41)]}, timeout=30)
        assert job.status_code == 202, job.text
    finally:
        stop.set()
        stop_server(server)
