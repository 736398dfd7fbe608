"""What a fork written in plain PyTorch does to the machinery, done as a forker would do it: each change gives the
right numbers, or stops where it happens with one line that names the misuse and the fix (docs/forking.md). With
one seed and with several."""

import dataclasses
import os
import subprocess
import sys

import pytest
import torch
import torch.nn as nn

import sac_continuous_action as sac
import td3_continuous_action as td3
from conftest import REPO, parse, script_command
from rl_utils import CudaGraph, parse_args, per_seed, stack_seeds
from rl_utils.seeds import join_seeds, model_of_seed, split_seeds

SEEDS = pytest.mark.parametrize("seeds", [[4], [4, 5, 6]], ids=["one seed", "three seeds"])


class Projected(nn.Module):
    """A network with a frozen random projection (a parameter without gradient) and a buffer drawn at build time, and
    a buffer its forward pass updates in place (a count of calls)."""

    def __init__(self):
        super().__init__()
        self.projection = nn.Linear(3, 3)
        self.projection.requires_grad_(False)
        self.register_buffer("mask", torch.randn(3).sign())
        self.register_buffer("calls", torch.zeros(()))
        self.head = nn.Linear(3, 1)

    def forward(self, x):
        self.calls.add_(1)
        return self.head(self.projection(x) * self.mask)


def built(seeds):
    """stack_seeds' networks, as main builds them: after seeding the process with its first seed."""
    torch.manual_seed(seeds[0])
    return stack_seeds(lambda: [Projected()], seeds, torch.device("cpu"))[0]


def loss_fn(x, net):
    return net(x).pow(2).mean()


@SEEDS
def test_a_frozen_parameter_stays_frozen_and_untrained(seeds):
    """requires_grad_(False) survives stacking: an optimizer that covers the whole network leaves it as built."""
    net = built(seeds)
    assert not net.projection.weight.requires_grad and net.head.weight.requires_grad
    frozen = net.projection.weight.clone()
    optimizer = torch.optim.Adam(net.parameters(), lr=0.1)
    for _ in range(3):
        optimizer.zero_grad()
        per_seed(loss_fn)(torch.randn(len(seeds), 8, 3), net).sum().backward()
        optimizer.step()
    assert torch.equal(net.projection.weight, frozen)


@SEEDS
def test_each_seed_has_its_own_buffers_and_updates_them_in_place(seeds):
    """A buffer drawn at build time is each seed's own, as a single-seed run of that seed draws it; a forward pass
    that updates a buffer in place updates each seed's; each seed's checkpoint and saved model holds its own."""
    alone = [built([seed]) for seed in seeds]
    net = built(seeds)
    x = torch.randn(len(seeds), 8, 3)
    out = per_seed(lambda x, net: net(x))(x, net)
    for k, single in enumerate(alone):
        assert torch.equal(net.mask[k] if len(seeds) > 1 else net.mask, single.mask)
        torch.testing.assert_close(out[k], single(x[k]))
    assert net.calls.tolist() == ([1.0] * len(seeds) if len(seeds) > 1 else 1.0)  # one call each
    state = {"nets": {"net": net.state_dict()}, "optimizers": {}, "envs": [None] * len(seeds)}
    shares = split_seeds(state, {}, [[] for _ in seeds], [f"r{k}" for k in range(len(seeds))])
    for k, single in enumerate(alone):
        assert torch.equal(shares[k]["nets"]["net"]["mask"], single.mask)
        assert torch.equal(model_of_seed({"net": net}, k, len(seeds))["net"]["mask"], single.mask)
    assert torch.equal(join_seeds(shares, {})["nets"]["net"]["mask"], net.mask)


@SEEDS
def test_a_tensor_without_the_seeds_dimension_is_refused_in_one_line(seeds):
    """per_seed cuts every tensor argument along its first dimension, one slice per seed: a tensor the seeds share
    (here a [batch] weight) would be cut; it is refused, naming the argument and the fix."""
    net = built(seeds)
    weights = torch.rand(8)

    def weighted_loss(x, net, weights):
        return (net(x).squeeze(-1) * weights).mean()

    with pytest.raises(TypeError) as refused:
        per_seed(weighted_loss)(torch.randn(len(seeds), 8, 3), net, weights)
    message = str(refused.value)
    assert "\n" not in message and message.startswith("per_seed(weighted_loss): argument 3 is a tensor of shape [8]")
    assert f"[{len(seeds)}, ...] with {len(seeds)} seed(s)" in message and "functools.partial" in message
    # the fix: a seeds dimension, or the shared tensor inside the function
    per_seed(weighted_loss)(torch.randn(len(seeds), 8, 3), net, weights.expand(len(seeds), 8))
    per_seed(lambda x, net: weighted_loss(x, net, weights))(torch.randn(len(seeds), 8, 3), net)


def forked_args(base, **fields):
    """A fork's Args: the base's with more flags (name: (type, default))."""
    extra = [(name, kind, dataclasses.field(default=default)) for name, (kind, default) in fields.items()]
    return dataclasses.make_dataclass("Args", extra, bases=(base.Args,))


def test_a_flag_a_fork_adds_has_only_the_rules_its_author_writes(monkeypatch):
    """A fork of TD3 that adds --alpha and --q-num (names SAC and OPARL check) gets no rule for them from rl_utils;
    SAC's own check of its --alpha is SAC's."""
    Args = forked_args(td3, alpha=(float, 0.2), q_num=(int, 2))
    Args.__module__ = td3.__name__  # as if defined in the forked script
    args = parse_args(Args, td3.check_args, ["--alpha", "-1", "--q-num", "0"])
    assert (args.alpha, args.q_num) == (-1.0, 0)
    with pytest.raises(SystemExit, match="--alpha must be >= 0, got -0.5"):
        parse(sac, ["--alpha", "-0.5"])


def test_a_graphed_update_given_a_changing_number_stops_saying_to_pass_a_tensor():
    """Each value of an update's arguments that are not tensors records a graph of its own (after eager warm-up
    calls): a number that changes at every call would run eagerly and record without end. The ninth value stops it.
    (The values before it are marked as seen here; recording itself needs a GPU, tests/test_cudagraphs.py.)"""
    update = CudaGraph(lambda batch, step: batch * step)
    update.calls = {(step,): 1 for step in range(8)}
    with pytest.raises(ValueError) as refused:
        update(torch.ones(2), 8)
    message = str(refused.value)
    assert "\n" not in message and message.startswith("CudaGraph(<lambda>): its arguments that are not tensors took 9")
    assert "pass a number that changes from call to call as a tensor" in message


@pytest.mark.parametrize("num_seeds", [1, 2])
@pytest.mark.parametrize("rebound", ["qf_target", "q_optimizer"])
def test_a_network_or_optimizer_bound_anew_stops_the_run_at_that_step(rebound, num_seeds, tmp_path):
    """A fork of TD3 that resets its target critics (or its critic's optimizer) by assignment, mid-run: the
    checkpoint and a recorded update would keep the old object. The run stops at that step, naming it and the fix."""
    anchor = "        run.log_episodes(infos, global_step)\n"
    new = {"qf_target": "copy.deepcopy(qf_target)", "q_optimizer": "adam(qf.parameters(), lr=args.learning_rate)"}[rebound]

    def edit(source):
        assert anchor in source
        fork = source.replace(anchor, anchor + f"        if global_step == 250:\n            {rebound} = {new}\n")
        return fork.replace("import functools\n", "import copy\nimport functools\n")

    result = run_fork(tmp_path, edit, num_seeds)
    assert result.returncode == 1
    line = result.stderr.strip().splitlines()[-1]
    what = "network" if rebound == "qf_target" else "optimizer"
    assert line.startswith(f"error: `{rebound}` was bound to a new object by step 250: ") and f"the {what} given" in line
    assert f"{rebound}.load_state_dict(fresh.state_dict()), fresh built as main builds it, by stack_seeds" in line


def run_fork(tmp_path, edit, num_seeds=1):
    """A fork of TD3 (td3_continuous_action.py with `edit(source)` applied) run for 400 steps on Pendulum-v1."""
    source = open(os.path.join(REPO, "td3_continuous_action.py")).read()
    (tmp_path / "fork_continuous_action.py").write_text(edit(source))
    flags = ["--env-id", "Pendulum-v1", "--total-timesteps", "400", "--learning-starts", "200", "--batch-size", "32"]
    flags += ["--eval-frequency", "400", "--eval-episodes", "1", "--num-seeds", str(num_seeds), "--run-name", "r{seed}"]
    command = script_command("td3", *flags)
    command[1] = str(tmp_path / "fork_continuous_action.py")
    env = {**os.environ, "PYTHONPATH": REPO}
    return subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)


def test_a_network_main_holds_but_does_not_checkpoint_is_refused_at_the_start(tmp_path):
    """A fork that adds a network (a second target critic, say) but not to run.start's nets would resume it from its
    initial weights: refused before the first step."""
    anchor = "    nets = {"
    result = run_fork(tmp_path, lambda s: s.replace(anchor, "    extra_critic = QEnsemble(obs_dim, action_dim)\n" + anchor, 1))
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: `extra_critic` is not in run.start's nets: a checkpoint would not hold it; add it there"
    )


def test_frozen_restores_what_each_parameter_was():
    """The actor step's freeze gives each parameter back its own requires_grad: a layer a fork froze for good stays
    frozen after the block."""
    from rl_utils import frozen

    qf = td3.QEnsemble(3, 1)
    qf[0].fc1.requires_grad_(False)  # a fork's pretrained, frozen first layer
    with frozen(qf):
        assert not any(p.requires_grad for p in qf.parameters())
    assert not qf[0].fc1.weight.requires_grad and not qf[0].fc1.bias.requires_grad
    assert all(p.requires_grad for name, p in qf.named_parameters() if not name.startswith("0.fc1"))


def test_the_ddpg_walk_in_docs_forking_applies_to_td3_and_trains(tmp_path, monkeypatch):
    """docs/forking.md's DDPG change, made to today's TD3 as its `diff` block reads: every line it removes is in TD3
    once, and the fork trains with one critic and steps its actor at every critic step."""
    import importlib.util
    import re

    with open(os.path.join(REPO, "docs", "forking.md")) as f:
        block = re.search(r"```diff\n(.*?)```", f.read(), re.S).group(1).splitlines()
    removed, added = [line[1:] for line in block if line[0] == "-"], [line[1:] for line in block if line[0] == "+"]
    with open(os.path.join(REPO, "td3_continuous_action.py")) as f:
        fork = f.read()
    assert len(removed) == len(added) == 4
    for old, new in zip(removed, added):
        assert fork.count(old + "\n") == 1, f"docs/forking.md's DDPG diff removes a line TD3 no longer has: {old.strip()}"
        fork = fork.replace(old + "\n", new + "\n")
    path = tmp_path / "ddpg_continuous_action.py"
    path.write_text(fork)
    spec = importlib.util.spec_from_file_location("ddpg_continuous_action", path)
    ddpg = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "ddpg_continuous_action", ddpg)  # as an import would; undone after the test
    spec.loader.exec_module(ddpg)
    monkeypatch.chdir(tmp_path)
    args = ddpg.Args(
        env_id="Pendulum-v1", total_timesteps=400, learning_starts=200, batch_size=32, eval_frequency=400, eval_episodes=1
    )
    result = ddpg.main(args)
    assert len(result["qf"]) == len(result["qf_target"]) == 1 and args.policy_noise == 0.0
    steps = [
        [s["step"].item() for s in result[name].state_dict()["state"].values()] for name in ("q_optimizer", "actor_optimizer")
    ]
    assert min(steps[0]) == max(steps[0]) == min(steps[1]) == max(steps[1]) > 0  # TD3 steps its actor every 2nd step
    assert (
        os.path.isdir(os.path.join(tmp_path, "runs"))
        and os.path.basename(result["run_dir"]).split("__")[1] == "ddpg_continuous_action"
    )
