"""The SDK's tests run against a real relfusiond: ``RELFUSION_URL`` (its token in
``RELFUSION_TOKEN``) and a TUM-layout sequence in ``RELFUSION_TEST_SEQUENCE``. The Rust test
``tests/tests/python_sdk.rs`` starts both and runs this suite from the built wheel."""

import os
from pathlib import Path

import pytest

import relfusion


def _env(name: str) -> str:
    value = os.environ.get(name)
    if not value:
        pytest.skip(f"{name} is not set (run through tests/tests/python_sdk.rs)")
    return value


@pytest.fixture
def url() -> str:
    return _env("RELFUSION_URL")


@pytest.fixture
def token() -> str:
    return _env("RELFUSION_TOKEN")


@pytest.fixture
def sequence() -> Path:
    return Path(_env("RELFUSION_TEST_SEQUENCE"))


@pytest.fixture
def client(url: str, token: str):
    with relfusion.Client(url, token) as c:
        yield c
