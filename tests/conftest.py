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
    """What a command handed the function this stands in for (``gearscan.replay.replay``, ``Reconstructor.for_gear``;
    ``calls``: its keyword arguments, one dict per call); the stub raises :attr:`Called` instead of running."""

    class Called(Exception):
        pass

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def __call__(self, *args, **kw):
        self.calls.append(kw)
        raise self.Called


@pytest.fixture
def replay_spy(monkeypatch) -> ReplaySpy:
    """``gearscan.replay.replay`` replaced by a :class:`ReplaySpy`: what a command hands the replay, without replaying."""
    import gearscan.replay as replay_module

    spy = ReplaySpy()
    monkeypatch.setattr(replay_module, "replay", spy)
    return spy


class OwnSupportDecoder:
    """A stand-in decoder whose model names its own fringe-support tests (``inference.predictor.NetworkSupport``'s
    fields); decoding with it is a test failure (the tests stop before the first burst)."""

    def __init__(self, per_burst_px: int | None, frame_fit_px: int | None) -> None:
        from gearscan.inference.predictor import NetworkSupport

        self.network_support = NetworkSupport(per_burst_px, frame_fit_px)

    def __call__(self, burst):
        raise AssertionError("a burst reached the stand-in decoder")


@pytest.fixture
def own_support_decoder() -> type[OwnSupportDecoder]:
    return OwnSupportDecoder


@pytest.fixture
def support_spy(monkeypatch) -> ReplaySpy:
    """``Reconstructor.for_gear`` replaced by a spy (``calls[-1]["network_support_px"]``: the test it was given); the
    run stops there (:attr:`ReplaySpy.Called`)."""
    from gearscan.recon.measure import Reconstructor

    spy = ReplaySpy()
    monkeypatch.setattr(Reconstructor, "for_gear", spy)
    return spy
