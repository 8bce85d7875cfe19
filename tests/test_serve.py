"""`apose serve` (apose_studio/service.py): a good request answers what the API answers for the same frame;
bad requests (bad JSON, wrong sizes, NaN intrinsics, a huge body, an unknown step or key) each get a 4xx with
the CLI's one-line message and the service keeps answering; a full queue answers 503 at once; a token, when
set, is required; the command itself starts, prints its address and serves."""

import base64
import http.client
import json
import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from apose_studio.estimation import truth_box

from .conftest import SAMPLES, free_port, rendered_frame, write_capture

PLANETARY = SAMPLES / "planetary_reducer" / "assembly.yaml"


def png_b64(img) -> str:
    return base64.b64encode(cv2.imencode(".png", img)[1].tobytes()).decode()


@pytest.fixture(scope="module")
def frame():
    return rendered_frame(PLANETARY, 2, 0, noise="realsense", seed=11)


def request_body(frame, **extra) -> dict:
    cam = frame.camera
    return {"rgb_png_b64": png_b64(frame.rgb[..., ::-1]), "depth_png_b64": png_b64((frame.depth * 1000).astype(np.uint16)),
            "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "depth_scale": 1.0},
            "step": 2, "box": list(truth_box(frame.base_mask())), **extra}


@pytest.fixture(scope="module")
def server():
    from apose_studio.service import EstimationService, make_server

    service = EstimationService(PLANETARY, queue=2)
    srv = make_server(service, "127.0.0.1", 0)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def call(srv, method, path, body=None, headers=None, raw: bytes | None = None):
    conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=120)
    data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
    conn.request(method, path, body=data, headers={"Content-Type": "application/json", **(headers or {})})
    r = conn.getresponse()
    doc = json.loads(r.read() or b"{}")
    conn.close()
    return r.status, doc


def test_a_good_request_answers_as_the_api_does(server, frame, tmp_path):
    from apose_studio.api import estimate_pose
    from apose_studio.data.dataset import load_capture
    from apose_studio.robot.handeye import hand_eye_from_data

    he = {"T_robot_camera": np.eye(4).tolist()}
    status, doc = call(server, "POST", "/estimate", request_body(frame, hand_eye=he))
    assert status == 200, doc
    capture = load_capture(write_capture(frame, tmp_path / "c"))  # the same frame as files: what the request carried
    est = estimate_pose(capture.rgb, capture.depth, capture.K, PLANETARY, 2, box=truth_box(frame.base_mask()),
                        hand_eye=hand_eye_from_data(he, "he"))
    assert doc["ok"] and doc["ok"] == est.ok and doc["confident"] == est.confident
    np.testing.assert_array_equal(np.asarray(doc["T_camera_part"]), est.T_camera_part)  # deterministic: the same bits
    np.testing.assert_array_equal(np.asarray(doc["T_robot_gripper_place"]), est.targets.T_robot_gripper_place)
    assert doc["part"] == "housing" and doc["step"] == 2 and "service" in doc["timings_s"]
    box = list(truth_box(frame.base_mask()))
    assert doc["mask"]["prompt_box"] == box and doc["mask"]["prompt_box_used"] == box  # the box as given, as used
    status, health = call(server, "GET", "/health")
    assert status == 200 and health["served"] >= 1 and health["steps"] == 4


def test_bad_requests_get_a_4xx_naming_the_problem_and_the_service_goes_on(server, frame):
    good = request_body(frame)
    bad_nan = json.dumps(good).replace('"fx": ' + str(frame.camera.fx), '"fx": NaN').encode()
    half = dict(good, depth_png_b64=png_b64((frame.depth[::2, ::2] * 1000).astype(np.uint16)))
    cases = [
        (b"{not json", 400, "not valid JSON"),
        (json.dumps([1, 2]).encode(), 400, "JSON object"),
        (json.dumps(dict(good, step=9)).encode(), 400, "steps 1..4"),
        (json.dumps(dict(good, step="2")).encode(), 400, "does not exist"),
        (json.dumps(dict(good, colour="red")).encode(), 400, "colour: unknown key"),
        (json.dumps(half).encode(), 400, "align depth"),
        (bad_nan, 400, "NaN"),
        (json.dumps(dict(good, camera=dict(good["camera"], fx=-5))).encode(), 400, "positive"),
        (json.dumps(dict(good, rgb_png_b64="%%%")).encode(), 400, "base64"),
        (json.dumps(dict(good, depth_png_b64=good["rgb_png_b64"])).encode(), 400, "depth"),
        (json.dumps(dict(good, box=[1, 2, 3])).encode(), 400, "4 numbers"),
        (json.dumps(dict(good, box="inf,0,10,10")).encode(), 400, "4 numbers"),
        (json.dumps(dict(good, box=[1e300, 0, 10, 10])).encode(), 400, "4 numbers"),
        (json.dumps(dict(good, box=[True, 0, 10, 10])).encode(), 400, "4 numbers"),
        (json.dumps(dict(good, hand_eye={"T_robot_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})).encode(),
         400, "not orthonormal"),
        (json.dumps(dict(good, hand_eye={"T_robot_camera": np.eye(4).tolist()}, grasp="handle")).encode(), 400,
         "its grasps: ring"),
        (b"\xff\xfe", 400, "UTF-8"),
        (json.dumps(dict(good, point=[300, 200])).encode(), 400, "box and point: give one way"),
        (json.dumps(dict(good, hand_eye={"T_robot_camera": np.eye(4).tolist()}, pick_box=[10, 10, 90, 90],
                         pick_point=[600, 50])).encode(), 400, "a box and a point: give one prompt"),
        (json.dumps(dict(good, camera=dict(good["camera"], cam_R_w2c=np.eye(3).reshape(-1).tolist(),
                                           cam_t_w2c=[0.29, 0.71, 0.5]))).encode(), 400, "multiply them by 1000"),
    ]
    for raw, status, words in cases:
        got, doc = call(server, "POST", "/estimate", raw=raw, headers={"Content-Type": "application/json"})
        assert got == status and words in doc.get("error", ""), (raw[:80], got, doc)
        assert "Traceback" not in doc.get("error", "")
    got, doc = call(server, "POST", "/estimate", raw=b"x", headers={"Content-Length": str(10 ** 9)})
    assert got == 413 and "over the" in doc["error"]  # refused from the header: the gigabyte is never read
    assert call(server, "GET", "/nowhere")[0] == 404 and call(server, "PUT", "/estimate", {})[0] == 405
    got, doc = call(server, "POST", "/estimate", good)
    assert got == 200 and doc["ok"]


def test_a_full_queue_answers_503_at_once(server, frame):
    body = request_body(frame)
    server.service.lock.acquire()  # an estimate under way: the next requests wait for it
    try:
        results = []
        threads = [threading.Thread(target=lambda: results.append(call(server, "POST", "/estimate", body)))
                   for _ in range(2)]
        for t in threads:
            t.start()
        deadline = time.time() + 60
        while server.service._busy < 2 and time.time() < deadline:
            time.sleep(0.05)
        t0 = time.perf_counter()
        status, doc = call(server, "POST", "/estimate", body)  # the queue (2) is full
        assert status == 503 and "busy" in doc["error"] and time.perf_counter() - t0 < 10
    finally:
        server.service.lock.release()
    for t in threads:
        t.join(120)
    assert [s for s, _ in results] == [200, 200]


def test_a_token_when_set_is_required(frame):
    from apose_studio.service import EstimationService, make_server

    srv = make_server(EstimationService(PLANETARY, queue=1), "127.0.0.1", 0, token="t" * 20)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        assert call(srv, "GET", "/health")[0] == 401
        assert call(srv, "GET", "/health", headers={"Authorization": "Bearer " + "u" * 20})[0] == 401
        assert call(srv, "GET", "/health", headers={"Authorization": "Bearer " + "t" * 20})[0] == 200
        assert call(srv, "POST", "/estimate", request_body(frame))[0] == 401
    finally:
        srv.shutdown()
        srv.server_close()
    assert make_server(EstimationService(PLANETARY, queue=1), "0.0.0.0", 0).token  # beyond loopback: always a token


def test_the_command_serves_and_stops():
    port = free_port()
    p = subprocess.Popen([sys.executable, "-m", "apose_studio.cli.commands", "serve", str(PLANETARY), "--port", str(port)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = p.stdout.readline()
        assert line.startswith(f"serve: http://127.0.0.1:{port}"), (line, p.stderr.read() if p.poll() is not None else "")
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        conn.request("GET", "/health")
        assert json.loads(conn.getresponse().read())["assembly"] == "planetary_reducer"
    finally:
        p.terminate()
        p.wait(30)
    bad = subprocess.run([sys.executable, "-m", "apose_studio.cli.commands", "serve", str(PLANETARY), "--param", "nope=1"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "nope" in bad.stderr and "Traceback" not in bad.stderr


def test_arrays_as_npy_answer_as_pngs_do_and_pickles_are_refused(server, frame):
    import io

    def npy(a) -> str:
        f = io.BytesIO()
        np.save(f, a, allow_pickle=True)
        return base64.b64encode(f.getvalue()).decode()

    png = request_body(frame)
    arrays = {k: v for k, v in png.items() if not k.endswith("_png_b64")}
    arrays.update(rgb_npy_b64=npy(np.ascontiguousarray(frame.rgb)), depth_npy_b64=npy((frame.depth * 1000).astype(np.uint16)))
    s1, d1 = call(server, "POST", "/estimate", png)
    s2, d2 = call(server, "POST", "/estimate", arrays)
    assert s1 == s2 == 200
    np.testing.assert_array_equal(np.asarray(d1["T_camera_part"]), np.asarray(d2["T_camera_part"]))
    for bad, words in ((dict(arrays, depth_npy_b64=npy(frame.depth)), "little-endian uint16"),
                       (dict(arrays, rgb_npy_b64=npy(np.array([{"a": 1}], dtype=object))), "little-endian uint8"),
                       (dict(arrays, rgb_npy_b64=base64.b64encode(b"not an array").decode()), "not a .npy"),
                       (dict(arrays, rgb_png_b64=png["rgb_png_b64"]), "give the rgb image once")):
        status, doc = call(server, "POST", "/estimate", bad)
        assert status == 400 and words in doc["error"], doc


def npz_body(frame, keys: dict | None = None, compressed: bool = False, **arrays) -> bytes:
    """numpy.savez's bytes: the frame's rgb and depth (mm) and the other keys as JSON text."""
    import io

    f = io.BytesIO()
    keys = {k: v for k, v in request_body(frame).items() if not k.endswith("_png_b64")} if keys is None else keys
    parts = {"rgb": np.ascontiguousarray(frame.rgb), "depth": (frame.depth * 1000).astype(np.uint16),
             "request": np.array(json.dumps(keys)), **arrays}
    (np.savez_compressed if compressed else np.savez)(f, **{k: v for k, v in parts.items() if v is not None})
    return f.getvalue()


def test_an_npz_body_answers_as_the_json_one_and_bad_archives_are_refused(server, frame):
    """The lowest-overhead body (no base64, no PNG decoding): the same answer, to the bit; archives that are not
    what they say are refused by what is wrong, before their members are decompressed past their limits."""
    import io
    import zipfile

    npz = {"Content-Type": "application/x-npz"}
    s1, d1 = call(server, "POST", "/estimate", request_body(frame))
    s2, d2 = call(server, "POST", "/estimate", raw=npz_body(frame), headers=npz)
    s3, d3 = call(server, "POST", "/estimate", raw=npz_body(frame, compressed=True), headers=npz)
    assert s1 == s2 == s3 == 200, (d2, d3)
    np.testing.assert_array_equal(np.asarray(d1["T_camera_part"]), np.asarray(d2["T_camera_part"]))
    np.testing.assert_array_equal(np.asarray(d1["T_camera_part"]), np.asarray(d3["T_camera_part"]))

    bomb = io.BytesIO()  # 200 MB of zeros deflated to ~200 kB, declared honestly: refused from the directory
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("rgb.npy", b"\0" * (200 * 2 ** 20))
        z.writestr("depth.npy", b"")
        z.writestr("request.npy", b"")
    liar = io.BytesIO()  # 20 MB, its directory entry claiming 1 kB: zipfile inflates no more than that, then its CRC fails
    with zipfile.ZipFile(liar, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("depth.npy", b"")
        z.writestr("request.npy", b"")
        z.writestr("rgb.npy", b"\0" * (20 * 2 ** 20))
    data = bytearray(liar.getvalue())
    cd = data.rindex(b"PK\x01\x02")  # the last central-directory entry (rgb.npy): its uncompressed size at +24
    data[cd + 24: cd + 28] = (1024).to_bytes(4, "little")
    many = io.BytesIO()  # a directory of many empty members: refused from the archive's end record
    with zipfile.ZipFile(many, "w") as z:
        for i in range(5000):
            z.writestr(f"{i}", b"")
    keys = {k: v for k, v in request_body(frame).items() if not k.endswith("_png_b64")}
    for body, status, words in (
            (many.getvalue(), 400, "holds 5000 members"), (b"PK not a zip", 400, "not an NPZ archive"),
            (npz_body(frame, extra=np.zeros(3)), 400, "expected exactly rgb, depth and request"),
            (npz_body(frame, depth=frame.depth), 400, "little-endian uint16"),
            (npz_body(frame, dict(keys, rgb_png_b64="x")), 400, "leave them out of request"),
            (npz_body(frame, dict(keys, step=9)), 400, "step: 9 does not exist"),
            (npz_body(frame, request=np.array([1, 2])), 400, "the request's JSON as one text"),
            (bomb.getvalue(), 413, "at most"),
            (bytes(data), 400, "damaged archive member")):
        got, doc = call(server, "POST", "/estimate", raw=body, headers=npz)
        assert got == status and words in doc["error"], (words, got, doc)
    assert call(server, "POST", "/estimate", raw=npz_body(frame), headers=npz)[0] == 200  # and it goes on


def test_who_a_connection_comes_from():
    from apose_studio.service import peer_of

    assert {peer_of(a) for a in ("127.0.0.1", "127.0.0.2", "127.255.0.9", "::1", "::ffff:127.0.0.1")} == {"loopback"}
    assert peer_of("2001:db8::1") == peer_of("2001:db8::ffff:2") != peer_of("2001:db8:0:1::1")  # one host, one /64
    assert peer_of("192.168.1.5") != peer_of("192.168.1.6") and peer_of("::ffff:10.0.0.1") == "10.0.0.1"


def test_bodies_that_parse_into_far_more_than_their_size_are_refused_unparsed(server, frame):
    """A JSON body of millions of tiny items (a 60 MB list of {} took 1.5 GB to parse) is counted before it is
    parsed; an NPZ member compressed another way or encrypted is named as such."""
    import io
    import zipfile

    for body in (b'{"camera": [' + b"{}," * 200_000 + b'{}]}', b'{"box": [' + b"0," * 300_000 + b"0]}",
                 json.dumps({f"k{i}": 0 for i in range(50_000)}).encode()):
        t = time.perf_counter()
        status, doc = call(server, "POST", "/estimate", raw=body)
        assert status == 400 and "JSON items" in doc["error"] and time.perf_counter() - t < 5, doc
    keys = {k: v for k, v in request_body(frame).items() if not k.endswith("_png_b64")}
    assert sum(json.dumps(dict(keys, hand_eye={"T_robot_camera": np.eye(4).tolist()})).count(c) for c in ",:[{") < 200
    f = io.BytesIO()
    with zipfile.ZipFile(f, "w", zipfile.ZIP_BZIP2) as z:
        for name in ("rgb.npy", "depth.npy", "request.npy"):
            z.writestr(name, b"x")
    status, doc = call(server, "POST", "/estimate", raw=f.getvalue(), headers={"Content-Type": "application/x-npz"})
    assert status == 400 and "compressed by method 12" in doc["error"], doc


def test_web_pages_and_other_names_are_refused(server, frame):
    """A page in a browser can post to 127.0.0.1 (a form or text/plain needs no CORS preflight) and can rebind
    its own name to 127.0.0.1: the service answers programs only, by its own address."""
    body = request_body(frame)
    port = server.server_address[1]
    for headers, status, words in (({"Origin": "https://evil.example"}, 403, "web page"),
                                   ({"Origin": "null"}, 403, "web page"),
                                   ({"Host": f"evil.example:{port}"}, 403, "not this service's address"),
                                   ({"Host": "127.0.0.1:1"}, 403, "not this service's address"),
                                   ({"Content-Type": "text/plain"}, 415, "application/json"),
                                   ({"Content-Type": "application/x-www-form-urlencoded"}, 415, "application/json")):
        got, doc = call(server, "POST", "/estimate", body, headers=headers)
        assert got == status and words in doc["error"], (headers, got, doc)
    assert call(server, "GET", "/health", headers={"Origin": "https://evil.example"})[0] == 403
    assert call(server, "GET", "/health", headers={"Host": f"localhost:{port}"})[0] == 200
    assert call(server, "POST", "/estimate", body)[0] == 200


def raw_request(srv, data: bytes, read: bool = True) -> bytes:
    import socket

    with socket.create_connection(srv.server_address[:2], timeout=60) as s:
        s.sendall(data)
        if not read:
            return b""
        out = b""
        while chunk := s.recv(65536):
            out += chunk
        return out


def test_header_tricks_and_oversized_frames_are_refused(server, frame):
    host = f"127.0.0.1:{server.server_address[1]}"
    body = json.dumps(request_body(frame)).encode()
    head = f"POST /estimate HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n"
    answers = {
        "chunked": raw_request(server, (head + "Content-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n").encode()
                               + b"0\r\n\r\nGET /health HTTP/1.1\r\n\r\n"),
        "two hosts": raw_request(server, (head + f"Host: {host}\r\nContent-Length: {len(body)}\r\n\r\n").encode() + body),
        "superscript length": raw_request(server, (head + "Content-Length: \u00b2\r\n\r\n").encode("latin-1") + b"xx"),
    }
    assert answers["chunked"].count(b"HTTP/1.") == 1 and b" 400 " in answers["chunked"]  # one answer: nothing smuggled
    assert b" 400 " in answers["two hosts"] and b"given twice" in answers["two hosts"]
    assert b" 411 " in answers["superscript length"]
    big = (np.ones((1300, 1900)) * 800).astype(np.uint16)  # 2.5 MP, over the default 2.3 MP
    status, doc = call(server, "POST", "/estimate", dict(request_body(frame), depth_png_b64=png_b64(big),
                                                         rgb_png_b64=png_b64(np.zeros((1300, 1900, 3), np.uint8))))
    assert status == 413 and "million pixels" in doc["error"]
    he = {"T_flange_camera": np.eye(4).tolist(), "T_robot_flange": np.eye(4).tolist()}
    status, doc = call(server, "POST", "/estimate", request_body(frame, hand_eye=he, T_robot_flange=np.eye(4).tolist()))
    assert status == 400 and "given twice" in doc["error"]
    status, doc = call(server, "POST", "/estimate", request_body(frame, hand_eye={"T_flange_camera": np.eye(4).tolist()}))
    assert status == 400 and doc["error"].startswith("T_robot_flange: missing")
    status, doc = call(server, "POST", "/estimate", request_body(frame, hand_eye={"T_robot_camera": np.eye(4).tolist()},
                                                                  grasp="handle"))
    assert status == 400 and doc["error"].startswith("grasp: handle")
    assert call(server, "POST", "/estimate", request_body(frame, orientation_prior=None))[0] == 200  # null: absent
    status, doc = call(server, "POST", "/estimate", request_body(frame, align_depth="yes"))
    assert status == 400 and doc["error"] == "align_depth: expected true or false"
    status, doc = call(server, "POST", "/estimate", dict(request_body(frame, align_depth=True), box=None, point=None))
    assert status == 400 and doc["error"].startswith("align_depth: the depth is compared")
    status, doc = call(server, "POST", "/estimate", request_body(frame, align_depth=True))
    assert status == 200 and doc["ok"] and doc["depth_shift_px"] == [0, 0]  # a render registered exactly


def test_slow_and_many_connections_do_not_lock_clients_out(frame, monkeypatch):
    """A client that sends its request a byte at a time is cut once ARRIVAL_S has passed since it connected; one
    address cannot hold more than MAX_PER_ADDRESS connections (the next is told 503 at once)."""
    import socket

    from apose_studio import service as svc

    monkeypatch.setattr(svc, "ARRIVAL_S", 1.5)
    srv = svc.make_server(svc.EstimationService(PLANETARY, queue=2), "127.0.0.1", 0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        slow = socket.create_connection(srv.server_address[:2], timeout=30)
        slow.sendall(b"POST /estimate HTTP/1.1\r\n")
        t0 = time.time()
        try:
            while time.time() - t0 < 20:
                slow.sendall(b"X")  # a header that never ends, a byte a while: each read is quick, the whole never comes
                time.sleep(0.3)
        except OSError:
            pass
        assert time.time() - t0 < 10, "the dawdling client was not cut"
        slow.close()
        held = [socket.create_connection(srv.server_address[:2], timeout=30) for _ in range(svc.MAX_PER_ADDRESS)]
        time.sleep(0.3)
        extra = raw_request(srv, b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert b" 503 " in extra and b"too many connections" in extra
        # another loopback address is the same machine: no more connections for it (else one local process
        # holds all MAX_CONNECTIONS from 127.0.0.2, .3, ...)
        other = socket.socket()
        other.bind(("127.0.0.2", 0))
        other.settimeout(30)
        other.connect(srv.server_address[:2])
        other.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        got = b""
        while chunk := other.recv(4096):
            got += chunk
        other.close()
        assert b" 503 " in got and b"too many connections" in got
        for s in held:
            s.close()
        time.sleep(2.0)
        assert call(srv, "GET", "/health")[0] == 200
        assert call(srv, "POST", "/estimate", request_body(frame))[0] == 200
    finally:
        srv.shutdown()
        srv.server_close()


def test_estimates_at_once_answer_the_same_bits_as_one_at_a_time(frame):
    """Two workers: frames estimated side by side (several rounds, so that their stages overlap in different
    ways; the cluttered one goes through Open3D's seeded RANSAC) answer exactly what each answers alone."""
    from apose_studio.service import EstimationService, make_server

    other = rendered_frame(PLANETARY, 2, 1, noise="kinect", clutter=True, seed=5)
    bodies = [request_body(frame), request_body(other)]
    service = EstimationService(PLANETARY, queue=4, workers=2)
    srv = make_server(service, "127.0.0.1", 0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        alone = [call(srv, "POST", "/estimate", b)[1] for b in bodies]
        assert all(d["ok"] for d in alone) and call(srv, "GET", "/health")[1]["workers"] == 2
        got: list = []

        def send(k: int) -> None:
            got.append((k, call(srv, "POST", "/estimate", bodies[k])[1]))

        for _ in range(3):
            threads = [threading.Thread(target=send, args=(k,)) for k in (0, 1, 1, 0)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
        assert len(got) == 12
        for k, doc in got:
            assert doc["T_camera_part"] == alone[k]["T_camera_part"] and doc["confident"] == alone[k]["confident"]
    finally:
        srv.shutdown()
        srv.server_close()
