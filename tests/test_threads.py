"""The thread policy (talkmesh.models.threads): step loops on STEP_THREADS threads, restored
after; worker processes on their share of the cores."""

from __future__ import annotations

import pytest
import torch

from talkmesh.errors import TalkmeshError
from talkmesh.models import threads
from talkmesh.models.threads import ENV, STEP_THREADS, step_threads, worker_threads


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_step_threads_sets_and_restores(two_threads, monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    with step_threads():
        assert torch.get_num_threads() == STEP_THREADS == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), step_threads():  # restored on errors too
        raise RuntimeError
    assert torch.get_num_threads() == 2


def test_the_environment_overrides_the_policy(two_threads, monkeypatch):
    monkeypatch.setenv(ENV, "0")  # PyTorch's own count
    with step_threads():
        assert torch.get_num_threads() == 2
    monkeypatch.setenv(ENV, "8")  # never more than PyTorch has
    with step_threads():
        assert torch.get_num_threads() == 2
    for bad in ("-1", "two"):
        monkeypatch.setenv(ENV, bad)
        with pytest.raises(TalkmeshError, match=ENV), step_threads():
            pass


def test_workers_share_the_cores():
    assert worker_threads(1, cpus=8) == 8
    assert worker_threads(3, cpus=8) == 2
    assert worker_threads(16, cpus=8) == 1  # never none
    assert worker_threads(0, cpus=4) == 4
    assert 1 <= worker_threads(2) <= threads.usable_cpus()


def test_meshtalk_samples_on_the_step_threads(two_threads, monkeypatch):
    from talkmesh.models.meshtalk.model import MeshTalkModel

    monkeypatch.delenv(ENV, raising=False)
    torch.manual_seed(0)
    net = MeshTalkModel(MeshTalkModel.tiny_config()).eval()
    seen = []
    sample = net.prior.sample

    def recording(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return sample(*args, **kwargs)

    monkeypatch.setattr(net.prior, "sample", recording)
    net.generate(torch.zeros(1, 8000), torch.zeros(1, net.num_vertices, 3))
    assert seen == [1] and torch.get_num_threads() == 2


def test_codetalker_and_faceformer_steps_run_on_the_step_threads(
    two_threads, monkeypatch, tiny_codetalker
):
    from talkmesh.models.codetalker import model as codetalker_model
    from talkmesh.models.faceformer import FaceFormer
    from talkmesh.models.faceformer.model import FrameGenerator

    monkeypatch.delenv(ENV, raising=False)
    seen = []
    exact = codetalker_model.generate_exact

    def recording(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return exact(*args, **kwargs)

    monkeypatch.setattr(codetalker_model, "generate_exact", recording)
    net = tiny_codetalker()
    net.generate(
        torch.zeros(1, 8000),
        torch.zeros(1, net.num_vertices, 3),
        styles=torch.tensor([0]),
        mode="exact",
    )
    assert seen == [1] and torch.get_num_threads() == 2
    ff = FaceFormer(FaceFormer.tiny_config()).eval()
    step = FrameGenerator.step
    counts = []

    def step_recording(self, *args, **kwargs):
        counts.append(torch.get_num_threads())
        return step(self, *args, **kwargs)

    monkeypatch.setattr(FrameGenerator, "step", step_recording)
    ff.generate(torch.zeros(1, 8000), torch.zeros(1, ff.num_vertices, 3), styles=torch.tensor([0]))
    assert counts and set(counts) == {1} and torch.get_num_threads() == 2


def test_the_server_takes_its_share_beside_its_workers(two_threads, monkeypatch):

    monkeypatch.setattr(threads, "usable_cpus", lambda: 8)
    threads.set_process_threads(None, 3 + 1)
    assert torch.get_num_threads() == 2  # 8 cores for the server and 3 workers
    threads.set_process_threads(None, 8 + 1)
    assert torch.get_num_threads() == 1
    threads.set_process_threads(3, 8 + 1)  # --torch-threads wins
    assert torch.get_num_threads() == 3
