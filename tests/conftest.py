"""Shared fixtures: a small default rig and renderers (built once per session)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def gear():
    from gearscan.core.gear import GearSpec

    return GearSpec()


@pytest.fixture(scope="session")
def gear_mesh(gear):
    return gear.mesh()


@pytest.fixture(scope="session")
def rig256():
    from gearscan.core.rig import default_rig

    return default_rig(256, 256)


@pytest.fixture(scope="session")
def clean_renderer(rig256, gear, gear_mesh):
    """Noise-free twin renderer of the default rig at 256x256."""
    from gearscan.twin.render import Optics, TwinRenderer

    return TwinRenderer(rig256, gear, Optics().noise_free(), mesh=gear_mesh)


@pytest.fixture(scope="session")
def noisy_renderer(rig256, gear, gear_mesh):
    from gearscan.twin.render import Optics, TwinRenderer

    return TwinRenderer(rig256, gear, Optics(), mesh=gear_mesh)


class ReplaySpy:
    """What a command handed ``gearscan.replay.replay`` (``calls``: its keyword arguments, one dict per call); the
    stub raises :attr:`Called` instead of replaying."""

    class Called(Exception):
        pass

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def __call__(self, recording, **kw):
        self.calls.append(kw)
        raise self.Called


@pytest.fixture
def replay_spy(monkeypatch) -> ReplaySpy:
    """``gearscan.replay.replay`` replaced by a :class:`ReplaySpy`: what a command hands the replay, without replaying."""
    import gearscan.replay as replay_module

    spy = ReplaySpy()
    monkeypatch.setattr(replay_module, "replay", spy)
    return spy
