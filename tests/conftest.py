"""Shared fixtures: procedural scenes from ``gdiff.synth`` (built once per test session)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def synth_tiny_scene():
    """The ``tiny`` :class:`gdiff.synth.SynthScene` (seed 0), not rendered: call
    ``.render(camera, state)`` / ``.cameras(split)`` on it."""
    from gdiff import synth

    return synth.build_scene("tiny", 0)


@pytest.fixture(scope="session")
def synth_tiny_dir(tmp_path_factory):
    """A rendered ``tiny`` scene folder (seed 0), shared read-only by the session's tests."""
    from gdiff import synth

    return synth.make_scene(tmp_path_factory.mktemp("synth") / "tiny", "tiny", 0)


@pytest.fixture
def torch_threads():
    """``torch_threads(n)`` sets torch's intra-op thread count inside a test; the count the
    test started with is restored when it ends (passed, failed or interrupted), so no test
    leaves the worker on another count for the tests after it."""
    import torch

    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)
