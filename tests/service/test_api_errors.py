"""The one exception handler: the project's errors become status codes and bodies through one table
(service/api/errors.py), registered by the app factory; errors outside it stay 500s."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from randt.core.errors import (
    AuthError,
    BadMessageError,
    ConflictError,
    DegenerateProblemError,
    ForbiddenError,
    FormatError,
    InvalidCloudError,
    InvalidRequestError,
    NotFoundError,
    RandtError,
    RegistrationFailedError,
    UnavailableError,
)
from randt.service.api.errors import HTTP_STATUS, status_of
from randt.service.app import create_app
from randt.service.matchers import MatcherProcessDiedError
from randt.service.sessions import MapInUseError
from randt.service.settings import ServiceSettings
from randt.service.store import MATCHER_FILENAME
from randt.wire.messages import encode, scan_from_arrays
from tests.service.test_matchers import _sweeps

#: (error, status, body, WWW-Authenticate) as the API has answered them since before the table.
CASES: list[tuple[RandtError, int, dict[str, str], str | None]] = [
    (InvalidRequestError("bbox is inverted"), 422, {"detail": "bbox is inverted"}, None),
    (BadMessageError("bad", code="malformed"), 422, {"detail": "bad"}, None),
    (InvalidCloudError("empty"), 422, {"detail": "empty"}, None),
    (FormatError("x.pcd: bad header"), 422, {"detail": "x.pcd: bad header"}, None),
    (AuthError("missing bearer token"), 401, {"detail": "missing bearer token"}, "Bearer"),
    (
        AuthError("wrong bearer token", challenge='Bearer error="invalid_token"'),
        401,
        {"detail": "wrong bearer token"},
        'Bearer error="invalid_token"',
    ),
    (ForbiddenError("mutations are disabled"), 403, {"detail": "mutations are disabled"}, None),
    (
        NotFoundError(resource="map", ident="nowhere"),
        404,
        {"detail": "map 'nowhere' not found", "resource": "map", "id": "nowhere"},
        None,
    ),
    (NotFoundError("x.pcd: no such file"), 404, {"detail": "x.pcd: no such file"}, None),
    (ConflictError("busy"), 409, {"detail": "busy"}, None),
    (MapInUseError("map 'm' is in use"), 409, {"detail": "map 'm' is in use"}, None),
    (UnavailableError("the service is not running"), 503, {"detail": "the service is not running"}, None),
]


@pytest.fixture()
def app_raising(tmp_path):
    """The real app (not started) with one extra route that raises the error it is given."""
    app = create_app(ServiceSettings(data_dir=tmp_path), with_zenoh=False)
    errors: list[BaseException] = []

    @app.get("/_raise")
    def _raise() -> None:
        raise errors[-1]

    return app, errors


@pytest.mark.parametrize(("error", "code", "body", "challenge"), CASES, ids=lambda c: str(c)[:40])
def test_each_error_class_has_its_status_and_body(app_raising, error, code, body, challenge) -> None:
    app, errors = app_raising
    errors.append(error)
    r = TestClient(app).get("/_raise")
    assert (r.status_code, r.json()) == (code, body)
    assert r.headers.get("www-authenticate") == challenge


@pytest.mark.parametrize(
    "error",
    [
        RegistrationFailedError("diverged"),
        DegenerateProblemError("flat", weak_directions=("tz",)),
        MatcherProcessDiedError("gone"),
        RandtError("store closed"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_errors_outside_the_table_stay_server_errors(app_raising, error) -> None:
    app, errors = app_raising
    errors.append(error)
    r = TestClient(app, raise_server_exceptions=False).get("/_raise")
    assert r.status_code == 500 and r.text == "Internal Server Error"
    assert status_of(error) is None


def test_the_most_specific_class_wins() -> None:
    assert status_of(ForbiddenError("x")) == 403 and isinstance(ForbiddenError("x"), AuthError)
    assert status_of(MapInUseError("x")) == 409
    assert set(HTTP_STATUS.values()) == {401, 403, 404, 409, 422, 503}


def test_a_service_that_is_not_running_answers_503(tmp_path) -> None:
    client = TestClient(create_app(ServiceSettings(data_dir=tmp_path), with_zenoh=False))  # no lifespan
    for path in ("/sessions", "/maps", "/maps/default/tiles"):
        r = client.get(path)
        assert (r.status_code, r.json()) == (503, {"detail": "the service is not running"}), path


def test_a_listed_session_without_a_readable_trajectory_is_not_found(tmp_path) -> None:
    """The store's damage surfaces as the tree's NotFoundError (SessionManager.stored_trajectory),
    answered 404 naming the session, not as a 500."""
    settings = ServiceSettings(data_dir=tmp_path, matcher_processes=0, flush_interval_s=0.2)
    with TestClient(create_app(settings, with_zenoh=False)) as client:
        mgr = client.app.state.service.sessions
        for seq, sweep in enumerate(_sweeps(2)):
            mgr.submit("v", encode(scan_from_arrays("v", "s", seq, seq * 100_000_000, sweep)))
        deadline = time.monotonic() + 60
        while client.get("/sessions/v/s").json().get("scans") != 2:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert client.post("/sessions/v/s/close").status_code == 403  # (no token configured)
        assert mgr.close("v", "s")
        assert len(client.get("/sessions/v/s/trajectory").json()["poses"]) == 2
        (mgr.store.session_dir("v", "s") / MATCHER_FILENAME).write_bytes(b"not an npz")
        r = client.get("/sessions/v/s/trajectory")
        assert r.status_code == 404
        body = r.json()
        assert (body["resource"], body["id"]) == ("session", "v/s")
        assert body["detail"].startswith("session 'v/s' has no readable trajectory: ")
