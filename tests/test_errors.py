"""The exception tree (core/errors.py and its subclasses elsewhere): the drawing in core/errors.py's
docstring holds every class under its parent, and every class survives pickling with its type,
message and attributes, as the matcher processes need (tests/service/test_matchers.py sends errors
through a real one)."""

from __future__ import annotations

import importlib
import pickle
import pkgutil
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from randt.cli import errors as cli_errors
from randt.clients import rest as clients_rest
from randt.core import datasets as core_datasets
from randt.core import errors as core_errors
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
    NotRelocalizedError,
    RandtError,
    RegistrationFailedError,
    UnavailableError,
)
from randt.service import matchers as service_matchers
from randt.service import ray_executor as service_ray_executor
from randt.service import sessions as service_sessions
from randt.service import store as service_store


def _subclasses(cls: type) -> set[type]:
    out = set()
    for sub in cls.__subclasses__():
        out |= {sub} | _subclasses(sub)
    return out


REPO = Path(__file__).resolve().parents[1]


def _import_every_module() -> list[str]:
    """Import every module of the distribution (the subpackages ``pyproject.toml`` maps, walked),
    so that every subclass of RandtError is defined; return their names."""
    package_dir = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    names = []
    for top in sorted(package_dir):
        package = importlib.import_module(top)
        names.append(top)
        for info in pkgutil.walk_packages(package.__path__, f"{top}."):
            if info.name.rpartition(".")[2] != "__main__":  # runs the CLI when imported
                importlib.import_module(info.name)
                names.append(info.name)
    return names


#: One class of the drawing: the tree's branches (``│``, ``├──``, ``└──``) before its name, four
#: characters a level.
_DRAWN = re.compile(r"^    (?P<branches>(?:[│ ]   )*(?:[├└]── )?)(?P<name>[A-Z]\w*Error)\b")


def _drawing(docstring: str) -> dict[str, str | None]:
    """The classes drawn in the ``::`` block of ``docstring``, each with the class drawn as its parent."""
    block = docstring.split("::\n\n", 1)[1].split("\n\n", 1)[0]
    drawn: dict[str, str | None] = {}
    parents: list[str] = []
    for line in block.splitlines():
        match = _DRAWN.match(line)
        assert match, f"not a line of the tree: {line!r}"
        depth = len(match["branches"]) // 4
        del parents[depth:]
        drawn[match["name"]] = parents[-1] if parents else None
        parents.append(match["name"])
    return drawn


def test_the_drawing_in_core_errors_holds_every_class_under_its_parent() -> None:
    assert len(_import_every_module()) > 50  # the walk found the modules, not only the packages
    assert core_errors.__doc__ is not None
    drawn = _drawing(core_errors.__doc__)
    classes = {RandtError} | _subclasses(RandtError)
    real = {cls.__name__ for cls in classes}
    assert len(real) == len(classes), "two error classes share a name"
    assert sorted(real - drawn.keys()) == [], "missing from the drawing in core/errors.py's docstring"
    assert sorted(drawn.keys() - real) == [], "drawn in core/errors.py but not a RandtError"
    for cls in classes - {RandtError}:
        parent = drawn[cls.__name__]
        assert parent in {base.__name__ for base in cls.__bases__}, f"{cls.__name__} drawn under {parent}"
    assert drawn["RandtError"] is None


def test_the_drawing_check_sees_a_missing_class_and_a_wrong_parent() -> None:
    assert core_errors.__doc__ is not None
    doc = core_errors.__doc__
    without = "\n".join(line for line in doc.splitlines() if "ApiNotFoundError" not in line)
    assert "ApiNotFoundError" not in _drawing(without)
    moved = doc.replace("│   └── ApiNotFoundError", "├── ApiNotFoundError    ")
    assert _drawing(doc)["ApiNotFoundError"] == "ApiError"
    assert _drawing(moved)["ApiNotFoundError"] == "RandtError"


def _examples() -> list[RandtError]:
    """One instance of every class of the tree, each with its attributes set (not the defaults)."""
    return [
        RandtError("root"),
        InvalidCloudError("scan: 3 points within 2.0-100.0 m"),
        DegenerateProblemError(
            "the geometry does not constrain 2 degree(s) of freedom",
            result={"T_target_source": np.arange(16.0).reshape(4, 4), "converged": True},
            weak_directions=("tx", "rz"),
        ),
        RegistrationFailedError("non-finite pose"),
        NotRelocalizedError("relocalization: the sweep's match to the map is not taken (0.31 inliers)"),
        FormatError("x.pcd: malformed header"),
        BadMessageError("points: 3 columns expected", code="bad_points"),
        InvalidRequestError("bbox is inverted"),
        NotFoundError("tile '3_4' of map 'm' not found", resource="tile", ident="3_4"),
        ConflictError("busy"),
        service_sessions.MapInUseError("map 'default' is in use by 1 running session(s)"),
        AuthError("wrong bearer token", challenge='Bearer error="invalid_token"'),
        ForbiddenError("mutating endpoints are disabled"),
        UnavailableError("the service is not running"),
        service_matchers.MatcherProcessError("in matcher process pid 7: Boom: x"),
        service_matchers.MatcherProcessDiedError("matcher process 1 (pid 7) died"),
        service_ray_executor.ConfigurationError('executor "ray" needs the ray package'),
        service_store.DataDirInUseError("data directory d is already open in another process"),
        core_datasets.NoScansError("d: no scan files (.bin .pcd .ply)"),
        cli_errors.PortInUseError("HTTP port 8080 on 127.0.0.1 is in use"),
        cli_errors.WrongInputError("d is a directory, a file is expected"),
        clients_rest.ApiError(500, "Internal Server Error", "http://127.0.0.1:8080/maps"),
        clients_rest.ApiNotFoundError(404, "map 'x' not found", "http://127.0.0.1:8080/maps/x"),
    ]


def _same_attributes(a: dict[str, object], b: dict[str, object]) -> None:
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, dict):
            _same_attributes(value, b[key])  # type: ignore[arg-type]
        else:
            np.testing.assert_equal(b[key], value, err_msg=key)


def test_the_examples_cover_every_class_of_the_tree() -> None:
    assert {type(e) for e in _examples()} == {RandtError} | _subclasses(RandtError)


@pytest.mark.parametrize("exc", _examples(), ids=lambda e: type(e).__name__)
def test_every_error_survives_pickling_with_its_type_message_and_attributes(exc: RandtError) -> None:
    exc.add_note("raised in matcher process pid 7")
    back = pickle.loads(pickle.dumps(exc))
    assert type(back) is type(exc)
    assert back.args == exc.args and str(back) == str(exc)
    assert back.__notes__ == ["raised in matcher process pid 7"]
    _same_attributes(exc.__dict__, back.__dict__)


def test_attributes_that_pickling_used_to_lose_come_back() -> None:
    """An __init__ whose arguments are not its ``args`` (ApiError formats three into one message)
    could not be rebuilt by the default pickling: ``cls(*args)`` raised TypeError."""
    err = clients_rest.ApiNotFoundError(404, "map 'x' not found", "http://h/maps/x")
    back = pickle.loads(pickle.dumps(err))
    assert (back.status, back.detail, back.url) == (404, "map 'x' not found", "http://h/maps/x")
    assert isinstance(back, NotFoundError) and str(back) == "HTTP 404 from http://h/maps/x: map 'x' not found"
    degenerate = pickle.loads(pickle.dumps(DegenerateProblemError("flat", weak_directions=("tz",))))
    assert degenerate.weak_directions == ("tz",) and degenerate.result is None
    assert pickle.loads(pickle.dumps(BadMessageError("late", code="stale"))).code == "stale"


def test_not_found_names_what_was_asked_for() -> None:
    err = NotFoundError(resource="map", ident="nowhere")
    assert str(err) == "map 'nowhere' not found" and (err.resource, err.ident) == ("map", "nowhere")
    assert isinstance(err, LookupError)
    plain = NotFoundError("x.pcd: no such file")
    assert str(plain) == "x.pcd: no such file" and plain.resource is None and plain.ident is None
