"""Who may talk to a studio (``studio/guard.py``): its own page, with its launch's token,
on its own host and origin; no file outside what it serves; and the viser internals the
guard wraps, where it was written against them."""

import inspect

import pytest

pytest.importorskip("viser")

from studio.app import Studio  # noqa: E402
from studio.photos import PhotoTarget  # noqa: E402

from .helpers import tiny_stack  # noqa: E402


def test_the_private_viser_module_the_guard_wraps_is_still_there():
    """``guard.guarded_server`` replaces ``viser.infra._infra.websockets``' ``serve``; a viser
    that moved it would run without the guard, so the pinned range must keep it."""
    from viser.infra import _infra

    serve = _infra.websockets.asyncio.server.serve
    assert {"process_request", "max_size"} <= set(inspect.signature(serve).parameters)


def test_no_request_reads_other_files(tmp_path, rng):
    import http.client

    stack = tiny_stack(tmp_path / "w.npz", rng)
    studio = Studio(PhotoTarget.open(stack), port=0)
    try:
        cookie = f"{studio.guard.cookie_name(studio.port)}={studio.guard.token}"
        for path in ["/../../../../etc/passwd", "/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
                     f"/{stack}", f"/..{stack}", "/" + "../" * 12 + str(stack)]:
            connection = http.client.HTTPConnection("127.0.0.1", studio.port, timeout=10)
            connection.request("GET", path, headers={"Cookie": cookie})
            response = connection.getresponse()
            assert response.status == 404, path
            connection.close()
    finally:
        studio.stop()


# --- who may talk to a studio: its own page, with its token ----------------------------------

def _get(port, path, **headers):
    import http.client

    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    connection.request("GET", path, headers=headers)
    response = connection.getresponse()
    result = response.status, dict(response.getheaders()), response.read()
    connection.close()
    return result


@pytest.fixture
def studio(tmp_path, rng):
    running = Studio(PhotoTarget.open(tiny_stack(tmp_path / "w.npz", rng)), port=0)
    yield running
    running.stop()


def test_the_page_needs_the_token_and_its_own_host(studio, capsys):
    port, token = studio.port, studio.guard.token
    assert studio.url == f"http://127.0.0.1:{port}/?token={token}"
    assert _get(port, "/")[0] == 403
    assert _get(port, "/?token=wrong")[0] == 403
    status, headers, page = _get(port, f"/?token={token}")
    assert status == 200 and b"<title>w.npz - palette-studio</title>" in page
    cookie = headers["Set-Cookie"].split(";")[0]
    assert "HttpOnly" in headers["Set-Cookie"] and "SameSite=Strict" in headers["Set-Cookie"]
    assert _get(port, "/", Cookie=cookie)[0] == 200
    for host in (f"attacker.example:{port}", f"localhost.attacker.example:{port}",
                 "127.0.0.1:1", ""):  # DNS rebinding: another name for our address
        assert _get(port, f"/?token={token}", Host=host)[0] == 403, host
    assert _get(port, f"/?token={token}", Host=f"localhost:{port}")[0] == 200
    assert "refused '/' from 127.0.0.1" in capsys.readouterr().err  # logged


def test_sockets_only_from_the_studios_own_page(studio, capsys):
    """A WebSocket from another origin, or without the token, is refused at the handshake;
    the studio's own page with the token gets in."""
    import viser
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    port, token = studio.port, studio.guard.token
    protocol = [f"viser-v{viser.__version__}"]
    own = f"http://127.0.0.1:{port}"
    for origin, query in [("http://attacker.example", token), ("http://127.0.0.1:1", token),
                          ("null", token), (None, token), (own, ""), (own, "wrong")]:
        with pytest.raises(InvalidStatus, match="403"):
            connect(f"ws://127.0.0.1:{port}/?token={query}", origin=origin,
                    subprotocols=protocol, open_timeout=10).close()
    with connect(f"ws://127.0.0.1:{port}/?token={token}", origin=own, subprotocols=protocol,
                 open_timeout=10) as socket_:
        assert socket_.protocol.state.name == "OPEN"
    err = capsys.readouterr().err
    assert "refused '/' from 127.0.0.1: a WebSocket from origin 'http://attacker.example'" in err
    assert "connected: 127.0.0.1" in err


def test_no_share_url_and_bounded_views(studio, capsys):
    from types import SimpleNamespace

    from studio.pictures import MAX_ASPECT, bounded_aspect

    assert studio.server.request_share_url() is None
    assert "refused a request for a public share URL" in capsys.readouterr().err
    for aspect, expected in [(1e12, MAX_ASPECT), (0.0, 1 / MAX_ASPECT), (float("nan"), 1.0),
                             (1.5, 1.5)]:
        assert bounded_aspect(SimpleNamespace(aspect=aspect)) == expected


def test_a_studio_beyond_loopback_warns_and_keeps_the_token(tmp_path, rng, capsys):
    studio = Studio(PhotoTarget.open(tiny_stack(tmp_path / "w.npz", rng)), host="0.0.0.0",
                    port=0)
    try:
        assert "warning: listening on 0.0.0.0" in capsys.readouterr().err
        assert studio.url.endswith(f"?token={studio.guard.token}")
        assert _get(studio.port, "/")[0] == 403
        assert _get(studio.port, f"/?token={studio.guard.token}")[0] == 200
    finally:
        studio.stop()


