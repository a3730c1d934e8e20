"""The small edges of issue 41 (item 6): bounds published as JSON Schema, bodies in another
encoding or with a Content-Encoding, labels with bidirectional controls, and (against a real
server) connections that send no request head, and bytes beyond a body's Content-Length."""
import json
import socket

import pytest

from tests.servers import free_port, start_server, stop_server
from tests.service.conftest import assert_problem

JSON = {"content-type": "application/json"}


def test_integer_query_bounds_are_published_as_minimum_and_maximum(client):
    spec = client.get("/openapi.json").json()
    params = [p for ops in spec["paths"].values() for op in ops.values() for p in op.get("parameters", [])
              if p["in"] == "query"]
    assert params
    text = json.dumps([p["schema"] for p in params])
    assert '"ge"' not in text and '"le"' not in text
    limit = next(p for p in spec["paths"]["/v1/jobs"]["get"]["parameters"] if p["name"] == "limit")
    assert (limit["schema"]["minimum"], limit["schema"]["maximum"]) == (1, 200)
    task_limit = next(p for p in spec["paths"]["/v1/jobs/{job_id}"]["get"]["parameters"] if p["name"] == "task_limit")
    assert task_limit["schema"]["anyOf"][0]["minimum"] == 1


def test_a_content_encoding_on_a_plain_body_is_415(client, example):
    resp = client.post("/v1/fits", content=json.dumps(example), headers={**JSON, "content-encoding": "gzip"})
    assert_problem(resp, 415, "Content-Encoding 'gzip'")


@pytest.mark.parametrize("encode", [lambda t: t.encode("utf-16"), lambda t: t.encode("utf-16-le"),
                                    lambda t: b"\xef\xbb\xbf" + t.encode()], ids=["utf-16", "utf-16-le", "bom"])
def test_a_body_in_utf16_or_with_a_byte_order_mark_is_400(client, example, encode):
    resp = client.post("/v1/jobs", content=encode(json.dumps({"requests": [example]})), headers=JSON)
    assert_problem(resp, 400, "UTF-8 JSON without a byte-order mark")


@pytest.mark.parametrize("control", ["\u202e", "\u2066", "\u200f", "\u061c"])
def test_a_label_with_a_bidirectional_control_is_refused(client, example, control):
    resp = client.post("/v1/jobs", content=json.dumps({"requests": [example], "label": f"run{control}1"}),
                       headers=JSON)
    assert_problem(resp, 422, "label")


def _exchange(port: int, data: bytes, timeout: float = 30.0) -> bytes:
    """What the server sends back before closing the connection (b"" if it closes without a word)."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(data)
        out = b""
        while chunk := sock.recv(65536):
            out += chunk
        return out


def test_a_real_server_closes_idle_connections_and_answers_bad_framing_as_a_problem(tmp_path):
    port = free_port()
    server = start_server(tmp_path, port, workers=1, GREYFIT_REQUEST_HEAD_SECONDS="1")
    try:
        # nothing sent, then half a header: closed (before, both were held open for ever; a
        # socket.timeout here fails the test)
        assert _exchange(port, b"") == b""
        assert _exchange(port, b"GET /healthz HTTP/1.1\r\nHost: x\r\n") == b""
        # a Content-Length shorter than the body: the rest is read as a request, which cannot be parsed
        lying = (b"POST /v1/fits HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 2\r\n\r\n"
                 b"{}" + b"\x01garbage that is not a request line\r\n\r\n")
        answer = _exchange(port, lying)
        head, _, body = answer[answer.rindex(b"HTTP/1.1 400 "):].partition(b"\r\n\r\n")
        assert b"content-type: application/problem+json" in head.lower(), answer
        assert json.loads(body)["status"] == 400
    finally:
        stop_server(server)
