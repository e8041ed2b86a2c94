# SPDX-License-Identifier: Apache-2.0
"""pugsd.pipeline_factory: load_torchscript's refusals with their exact messages and no chained
traceback, the loaded network in eval mode, make_pipeline loading a network only for
proposer = "torchscript"."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pugsd.config import CoreConfig, GraspConfig
from pugsd.errors import PugsdError
from pugsd.pipeline_factory import load_torchscript, make_pipeline


def _refusal(path: Path | str) -> PugsdError:
    with pytest.raises(PugsdError) as exc:
        load_torchscript(path)
    assert type(exc.value) is PugsdError and exc.value.__cause__ is None
    return exc.value


def test_a_missing_file_or_a_directory_is_no_model(tmp_path: Path) -> None:
    missing = tmp_path / "nope.pt"
    assert str(_refusal(missing)) == f"grasp.model_path: no TorchScript model at {missing}"
    assert str(_refusal(str(tmp_path))) == f"grasp.model_path: no TorchScript model at {tmp_path}"


def test_a_file_that_is_no_torchscript_names_the_file(tmp_path: Path) -> None:
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model")
    err = _refusal(junk)
    assert err.__suppress_context__  # one line for the CLI, no chained torch traceback
    msg = str(err)
    assert msg.startswith(f"grasp.model_path: cannot load {junk} as TorchScript: "), msg
    assert len(msg) > len(f"grasp.model_path: cannot load {junk} as TorchScript: ")


def test_the_loaded_network_is_in_eval_mode_and_on_the_cpu(tmp_path: Path) -> None:
    net = torch.jit.script(torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.Dropout(0.5)))
    net.train()
    path = tmp_path / "net.pt"
    net.save(str(path))
    model = load_torchscript(str(path))
    assert not model.training
    assert all(not m.training for m in model.modules())
    assert {p.device.type for p in model.parameters()} == {"cpu"}
    x = torch.ones(1, 2)
    assert torch.equal(model(x), model(x))  # dropout off: deterministic


def test_make_pipeline_loads_a_network_only_for_the_torchscript_proposer(tmp_path: Path) -> None:
    missing = tmp_path / "missing.pt"
    # the other proposers never read model_path, even when it names no file
    for proposer, name in (("single_contact", "SingleContactProposer"), ("antipodal", "AntipodalProposer")):
        pipe = make_pipeline(CoreConfig(grasp=GraspConfig(proposer=proposer, model_path=str(missing))))
        assert type(pipe.proposer).__name__ == name
    with pytest.raises(PugsdError, match=f"^grasp.model_path: no TorchScript model at {missing}$"):
        make_pipeline(CoreConfig(grasp=GraspConfig(proposer="torchscript", model_path=str(missing))))


def test_make_pipeline_passes_the_seed() -> None:
    pipe = make_pipeline(CoreConfig(), seed=17)
    assert pipe.seed == 17
