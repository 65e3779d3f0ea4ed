"""Collections: streaming two-pass decomposition into Zarr stacks, videos in and out, resume,
and the same result on a local dask cluster."""

import json

import numpy as np
import pytest

av = pytest.importorskip("av")
zarr = pytest.importorskip("zarr")

import palette_core.collection as collection  # noqa: E402
import palette_core.sources as sources  # noqa: E402
from palette_core import decompose, read_stack  # noqa: E402
from palette_core.cli import decompose as decompose_cli  # noqa: E402
from palette_core.cli import recolor  # noqa: E402
from palette_core.collection import decompose_collection  # noqa: E402

from .helpers import expect_error, weight_invariants  # noqa: E402


def make_video(path, rng, frames=6, size=(48, 64), fps=12, keyframe_every=250):
    """A short H.264 clip of drifting colour blobs, generated here (never committed)."""
    yy, xx = np.mgrid[0:size[0], 0:size[1]]
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=fps, options={
            "g": str(keyframe_every), "keyint_min": str(keyframe_every), "sc_threshold": "0"})
        stream.height, stream.width, stream.pix_fmt = *size, "yuv420p"
        for i in range(frames):
            image = np.stack([(xx * 4 + i * 10) % 256, (yy * 5) % 256,
                              (xx + yy + 40 * i) % 256], -1)
            frame = av.VideoFrame.from_ndarray(image.astype(np.uint8), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    return path


def test_streaming_matches_the_in_memory_decomposition(photo_dir, tmp_path):
    store = str(tmp_path / "w.zarr")
    done = decompose_collection([photo_dir], store, k=5, progress=False)
    in_memory = decompose([photo_dir], k=5).stack
    streamed = read_stack(store)
    assert np.array_equal(streamed.palette, in_memory.palette)
    assert streamed.names == in_memory.names == done.names
    for a, b in zip(streamed.weights, in_memory.weights):
        assert np.allclose(a, b, atol=1e-6)
        weight_invariants(a.reshape(-1, a.shape[-1]), streamed.palette, None)


def test_a_video_in_and_out(tmp_path, rng, capsys):
    clip = make_video(tmp_path / "clip.mp4", rng)
    store = tmp_path / "w.zarr"
    assert decompose_cli.main([str(clip), "-k", "4", "-o", str(store)]) == 0
    stack = read_stack(store)
    assert stack.names == [f"clip.mp4#{i:06d}" for i in range(6)]
    assert stack.meta["videos"] == {"clip.mp4": 12.0}
    palette = tmp_path / "p.json"
    palette.write_text(json.dumps({"palette": ["#ff0000", "#00ff00", "#0000ff", "#ffffff"]}))
    assert recolor.main([str(store), "--palette", str(palette), "-o", str(tmp_path / "out")]) == 0
    with av.open(str(tmp_path / "out" / "clip.mp4")) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
        assert float(stream.average_rate) == 12.0
    assert len(frames) == 6 and frames[0].shape == (48, 64, 3)
    assert recolor.main([str(store), "--palette", str(palette), "-o", str(tmp_path / "png"),
                         "--frames"]) == 0
    assert sorted(p.name for p in (tmp_path / "png").iterdir())[0] == "clip.mp4#000000.png"
    capsys.readouterr()
    expect_error(decompose_cli.main, [str(clip), "-o", str(tmp_path / "w.npz")],
                 "--output: videos are decomposed into a Zarr stack", capsys)


def test_a_killed_second_pass_resumes(photo_dir, tmp_path, monkeypatch, capsys):
    store = str(tmp_path / "w.zarr")
    calls = []
    write = collection.write_task

    def write_then_stop(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return write(*args, **kwargs)

    monkeypatch.setattr(collection, "write_task", write_then_stop)
    with pytest.raises(KeyboardInterrupt):
        decompose_collection([photo_dir], store, k=5, progress=False)
    monkeypatch.setattr(collection, "write_task", write)
    with pytest.raises(Exception, match="incomplete"):
        read_stack(store)
    capsys.readouterr()
    expect_error(decompose_cli.main, [str(photo_dir), "-k", "5", "-o", store], "--resume",
                 capsys)
    assert decompose_cli.main([str(photo_dir), "-k", "5", "-o", store, "--resume"]) == 0
    fresh = decompose_collection([photo_dir], str(tmp_path / "f.zarr"), k=5, progress=False)
    resumed = read_stack(store)
    assert np.array_equal(resumed.palette, fresh.palette.vertices.astype(np.float32))
    for a, b in zip(resumed.weights, read_stack(tmp_path / "f.zarr").weights):
        assert np.array_equal(a, b)


def test_video_tasks_start_at_key_frames_and_seek_there(tmp_path, rng, monkeypatch):
    clip = make_video(tmp_path / "clip.mp4", rng, frames=9, keyframe_every=3)
    source = sources.find_sources([clip])[0]
    assert source.keyframes == (0, 3, 6)
    monkeypatch.setattr(collection, "TASK_MEGAPIXELS", 4 * 48 * 64 / 1e6)  # 4 frames a task
    assert [(t.start, t.stop) for t in collection.plan_tasks([source])] == [(0, 6), (6, 9)]
    whole = [pixels for pixels, _ in sources.read_frames(source)]
    for start, stop in [(3, 5), (4, 9), (7, 8)]:
        part = [pixels for pixels, _ in sources.read_frames(source, start, stop)]
        assert len(part) == stop - start
        assert all(np.array_equal(a, b) for a, b in zip(part, whole[start:stop]))


def test_a_local_dask_cluster_gives_the_same_stack(photo_dir, tmp_path, rng, monkeypatch):
    make_video(photo_dir / "clip.mp4", rng, frames=6, keyframe_every=2)
    monkeypatch.setattr(collection, "TASK_MEGAPIXELS", 2 * 48 * 64 / 1e6)  # tasks mid-video
    single = decompose_collection([photo_dir], str(tmp_path / "one.zarr"), k=5, progress=False)
    assert decompose_cli.main([str(photo_dir), "-k", "5", "-o", str(tmp_path / "two.zarr"),
                               "--workers", "2"]) == 0
    one, two = read_stack(tmp_path / "one.zarr"), read_stack(tmp_path / "two.zarr")
    assert np.array_equal(two.palette, single.palette.vertices.astype(np.float32))
    assert one.names == two.names and len(one.names) == 9
    for a, b in zip(one.weights, two.weights):
        assert np.allclose(a, b, atol=1e-6)


# --- outputs never delete what they did not create ------------------------------------------

def _user_folder(path):
    path.mkdir()
    (path / "thesis.txt").write_text("years of work")
    return path


@pytest.mark.parametrize("name", ["out.zarr", "out"])
@pytest.mark.parametrize("force", [[], ["--force"]])
def test_a_users_folder_is_never_replaced_by_a_store(photo_dir, tmp_path, capsys, name, force):
    folder = _user_folder(tmp_path / name)
    expect_error(decompose_cli.main, [str(photo_dir), "-k", "5", "-o", str(folder), *force],
                 "is not a weight stack store", capsys)
    assert (folder / "thesis.txt").read_text() == "years of work"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize("output", ["photos", "photos/sub", "photos/w.zarr", "."])
def test_an_output_among_the_inputs_is_refused_before_anything_is_opened(photo_dir, tmp_path,
                                                                         capsys, monkeypatch,
                                                                         output):
    monkeypatch.chdir(photo_dir)
    before = sorted(p.relative_to(photo_dir) for p in photo_dir.rglob("*"))
    target = str(tmp_path / output) if output != "." else "."
    expect_error(decompose_cli.main, [str(photo_dir), "-o", target, "--force"],
                 "would land among the inputs", capsys)
    assert sorted(p.relative_to(photo_dir) for p in photo_dir.rglob("*")) == before


def test_force_replaces_only_a_store_of_ours(photo_dir, tmp_path, capsys):
    store = tmp_path / "w.zarr"
    assert decompose_cli.main([str(photo_dir), "-k", "5", "-o", str(store)]) == 0
    capsys.readouterr()
    expect_error(decompose_cli.main, [str(photo_dir), "-k", "4", "-o", str(store)], "--force",
                 capsys)
    assert len(read_stack(store).palette) == 5
    assert decompose_cli.main([str(photo_dir), "-k", "4", "-o", str(store), "--force"]) == 0
    assert len(read_stack(store).palette) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos", "w.palette.json",
                                                          "w.palette.png", "w.zarr"]


def test_harmonize_never_replaces_a_users_folder(photo_dir, tmp_path, capsys):
    from harmonize.cli import main as harmonize

    assert decompose_cli.main([str(photo_dir), "-k", "5", "-o", str(tmp_path / "w.npz")]) == 0
    capsys.readouterr()
    folder = _user_folder(tmp_path / "mine.zarr")
    expect_error(harmonize, [str(tmp_path / "w.npz"), "--template", "triad", "-o", str(folder),
                             "--force"], "is not a weight stack store", capsys)
    assert (folder / "thesis.txt").exists()


# --- crafted and damaged stores and videos: one line, exit 2 ---------------------------------

def _store(tmp_path, names=("a.png", "b.png"), size=(3, 4), meta=None, basis="additive",
           order=1):
    """A valid Zarr stack written by the package, to be damaged by the test."""
    from palette_core.basis import Basis, n_terms
    from palette_core.stack import WeightStack
    from palette_core.stack.zarr import write_zarr_stack

    m = n_terms(4, Basis(basis), order)
    weights = [np.full((*size, m), 1 / m, np.float32) for _ in names]
    stack = WeightStack(np.eye(4, 3, dtype=np.float32), weights, list(names), "mvc",
                        Basis(basis), order, meta=meta or {})
    write_zarr_stack(stack, tmp_path / "w.zarr")
    return tmp_path / "w.zarr"


def _edit(path, change):
    """Rewrite the zarr.json at ``path`` through ``change(dict)``."""
    data = json.loads((path / "zarr.json").read_text())
    change(data)
    (path / "zarr.json").write_text(json.dumps(data))


def _attrs(**values):
    return lambda data: data["attributes"].update(values)


def _chunk(store, array="weights_0000"):
    return next(p for p in (store / array).rglob("*") if p.is_file() and p.name != "zarr.json")


CRAFTED = {
    "array outside": (lambda s: _edit(s, _attrs(arrays={"a.png": "../x/weights_0000",
                                                        "b.png": "weights_0001"})),
                      "arrays must map"),
    "no complete marker": (lambda s: __import__("shutil").rmtree(s / "complete"), "incomplete"),
    "missing chunk": (lambda s: _chunk(s).unlink(), "miss 1 of 1 chunks"),
    "terapixel": (lambda s: _edit(s / "weights_0000", lambda d: d.update(
        shape=[1_000_000, 1_000_000, 4])), "at most"),
    "meta a list": (lambda s: _edit(s, _attrs(meta="[]")), "meta must be a JSON object"),
    "meta deep": (lambda s: _edit(s, _attrs(meta="[" * 100_000 + "]" * 100_000)),
                  "malformed attributes"),
    "attributes deep": (lambda s: (s / "zarr.json").write_text(
        '{"zarr_format": 3, "node_type": "group", "attributes": {"x": '
        + "[" * 100_000 + "]" * 100_000 + "}}"), "not a readable Zarr weight stack"),
    "order 1000": (lambda s: _edit(s, _attrs(basis="transport", order=1000)), "channels"),
    "names not strings": (lambda s: _edit(s, _attrs(names=[1, 2])), "list of strings"),
}


@pytest.mark.parametrize("case", CRAFTED, ids=list(CRAFTED))
def test_crafted_stores_are_refused_before_anything_is_read(tmp_path, capsys, case):
    damage, message = CRAFTED[case]
    store = _store(tmp_path)
    damage(store)
    expect_error(recolor.main, [str(store), "--palette", str(_palette(tmp_path)), "-o",
                                str(tmp_path / "out")], message, capsys)
    assert not (tmp_path / "out").exists()


def _palette(tmp_path):
    from palette_core.palette_file import write_palette_json

    write_palette_json(tmp_path / "p.json", np.eye(4, 3)[::-1])
    return tmp_path / "p.json"


def test_a_truncated_chunk_names_the_image(tmp_path, capsys):
    store = _store(tmp_path)
    chunk = _chunk(store, "weights_0001")
    chunk.write_bytes(chunk.read_bytes()[:7])
    expect_error(recolor.main, [str(store), "--palette", str(_palette(tmp_path)), "-o",
                                str(tmp_path / "out")], "weights of b.png cannot be read", capsys)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("fps, size, message", [(float("nan"), (2, 2), "frame rate of clip.mp4"),
                                                (1e9, (2, 2), "frame rate of clip.mp4"),
                                                (12, (1, 1), "at least 2x2")])
def test_video_frame_rates_and_sizes(tmp_path, capsys, fps, size, message):
    names = [f"clip.mp4#{i:06d}" for i in range(3)]
    store = _store(tmp_path, names, size, meta={"videos": {"clip.mp4": 12}})
    _edit(store, _attrs(meta=json.dumps({"videos": {"clip.mp4": fps}})))
    expect_error(recolor.main, [str(store), "--palette", str(_palette(tmp_path)), "-o",
                                str(tmp_path / "out")], message, capsys)
    assert not (tmp_path / "out").exists()


def test_a_transport_stack_round_trips_through_a_store(tmp_path, capsys):
    """palette-harmonize writes a transport stack into a store that reads back."""
    from harmonize.cli import main as harmonize
    from palette_core.basis import Basis
    from palette_core.stack import WeightStack, write_stack

    rng = np.random.default_rng(3)
    weights = [rng.random((3, 4, 15)).astype(np.float32)]
    write_stack(WeightStack(np.array([[.9, .1, .1], [.1, .8, .2], [.1, .2, .9], [.9, .9, .2]],
                                     np.float32), weights, ["a.png"], "simulated",
                            Basis.TRANSPORT, 2), tmp_path / "t.npz")
    assert harmonize([str(tmp_path / "t.npz"), "--template", "triad", "-o",
                      str(tmp_path / "t.zarr")]) == 0
    back = read_stack(tmp_path / "t.zarr")
    assert back.basis == Basis.TRANSPORT and back.order == 2
    assert np.array_equal(back.weights[0], weights[0])


def _mjpeg_with_a_giant_frame(path, frames=4):
    """An MJPEG AVI whose third frame's header claims 65520 x 65520 pixels (the container
    declares the frame count, so the first decode is pass 1's)."""
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("mjpeg", rate=12)
        stream.width, stream.height, stream.pix_fmt = 32, 16, "yuvj420p"
        for i in range(frames):
            image = np.full((16, 32, 3), 40 * i, np.uint8)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    data = bytearray(path.read_bytes())
    sof = [i for i in range(len(data) - 1) if data[i:i + 2] == b"\xff\xc0"][2]
    data[sof + 5:sof + 9] = (65520).to_bytes(2, "big") * 2
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("make, message", [
    (lambda p, rng: p.write_bytes(make_video(p, rng, frames=12).read_bytes()[:1500]),
     "clip.mp4"),
    (lambda p, rng: _mjpeg_with_a_giant_frame(p), "cannot decode video"),
])
def test_damaged_videos_are_one_line(tmp_path, rng, capsys, make, message):
    clip = tmp_path / ("clip.mp4" if message == "clip.mp4" else "clip.avi")
    make(clip, rng)
    assert decompose_cli.main([str(clip), "-o", str(tmp_path / "w.zarr")]) == 2
    err = capsys.readouterr().err  # the error may follow pass 1's progress bar
    assert message in err.strip().splitlines()[-1] and "Traceback" not in err
    assert not any(p.name.startswith(("w.", ".w.")) for p in tmp_path.iterdir())


# --- dask: addresses and worker counts checked before dask reads anything -------------------

@pytest.fixture
def fake_scheduler():
    """A loopback server that accepts and then sends ``greeting`` (or nothing): ``start(greeting)
    -> address``."""
    import socket
    import threading

    servers = []

    def start(greeting: bytes) -> str:
        server = socket.create_server(("127.0.0.1", 0))
        server.settimeout(5)
        servers.append(server)

        def serve():
            try:
                connection, _ = server.accept()
            except OSError:
                return
            with connection:
                connection.sendall(greeting)
                connection.settimeout(5)
                try:
                    connection.recv(1)  # hold the connection open until the client leaves
                except OSError:
                    pass

        threading.Thread(target=serve, daemon=True).start()
        return f"tcp://127.0.0.1:{server.getsockname()[1]}"

    yield start
    for server in servers:
        server.close()


@pytest.mark.parametrize("greeting, message", [
    (b"", "did not answer within 0.5 s"),
    (b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n",
     "does not answer like a dask scheduler"),
])
def test_a_scheduler_that_is_not_one(photo_dir, tmp_path, capsys, monkeypatch, fake_scheduler,
                                     greeting, message):
    import palette_core.cluster

    monkeypatch.setattr(palette_core.cluster, "CONNECT_TIMEOUT_S", 0.5)
    expect_error(decompose_cli.main, [str(photo_dir), "-o", str(tmp_path / "w.zarr"),
                                      "--scheduler", fake_scheduler(greeting)], message, capsys)
    assert not any(p.name.startswith(("w.", ".w.")) for p in tmp_path.iterdir())


@pytest.mark.parametrize("options, message", [
    (["--scheduler", "tls://127.0.0.1:1"], "needs dask's TLS settings"),
    (["--scheduler", "ws://127.0.0.1:1"], "must be tcp://HOST:PORT"),
    (["--scheduler", "tcp://127.0.0.1"], "must be tcp://HOST:PORT"),
    (["--workers", "100000"], "--workers: must be 1 to"),
    (["--workers", "0"], "--workers: must be 1 to"),
    (["--workers", "1", "--scheduler", "tcp://127.0.0.1:1"], "not both"),
])
@pytest.mark.parametrize("output", ["w.zarr", "w.npz"])
def test_dask_options_are_checked(photo_dir, tmp_path, capsys, options, message, output):
    if output == "w.npz" and options[0] == "--scheduler":
        message = "--output: a cluster and resuming need a Zarr stack"
    expect_error(decompose_cli.main, [str(photo_dir), "-o", str(tmp_path / output), *options],
                 message, capsys)


@pytest.mark.parametrize("container, codec", [(".webm", "vp9"), (".mkv", "h264"),
                                               (".avi", "mpeg4"), (".mov", "h264")])
def test_recoloured_videos_keep_their_container(tmp_path, rng, container, codec):
    """The encoder follows the video's container: a .webm is written as VP9, not H.264."""
    names = [f"clip{container}#{i:06d}" for i in range(4)]
    store = _store(tmp_path, names, (16, 24), meta={"videos": {f"clip{container}": 10}})
    assert recolor.main([str(store), "--palette", str(_palette(tmp_path)), "-o",
                         str(tmp_path / "out")]) == 0
    with av.open(str(tmp_path / "out" / f"clip{container}")) as clip:
        assert clip.streams.video[0].codec_context.name == codec
        assert sum(1 for _ in clip.decode(video=0)) == 4


# --- one weight-method registry for images in memory and streams ----------------------------

def test_a_registered_per_colour_method_streams_and_a_spatial_one_is_refused(
        photo_dir, tmp_path, capsys, monkeypatch):
    import palette_core.weights as weights

    def nearest(colours, poly):
        """One-hot weights of the nearest palette colour."""
        distance = np.linalg.norm(colours[:, None] - poly.vertices[None], axis=-1)
        return np.eye(len(poly.vertices))[np.argmin(distance, axis=1)]

    monkeypatch.setitem(weights.WEIGHT_METHODS, "nearest", nearest)
    stream = decompose_collection([photo_dir], str(tmp_path / "w.zarr"), k=5, progress=False,
                                  method="nearest")
    memory = decompose([photo_dir], k=5, method="nearest")
    stored = read_stack(tmp_path / "w.zarr")
    assert stored.method == "nearest" and stored.names == memory.stack.names
    assert np.array_equal(stored.palette, stream.palette.vertices.astype(np.float32))
    for a, b in zip(stored.weights, memory.stack.weights):
        assert np.array_equal(a, b) and set(np.unique(a)) <= {0, 1}
    expect_error(decompose_cli.main, [str(photo_dir), "--method", "rgbxy", "-o",
                                      str(tmp_path / "r.zarr")], "needs whole images", capsys)
