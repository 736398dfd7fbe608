"""What a fork written in plain PyTorch does to the machinery, done as a forker would do it: each change gives the
right numbers, or stops where it happens with one line that names the misuse and the fix (docs/forking.md). With
one seed and with several."""

import ast
import collections
import copy
import dataclasses
import enum
import functools
import io
import os
import random
import re
import sys
import textwrap
import types
import typing

import numpy as np
import pytest
import torch
import torch.nn as nn

import sac_continuous_action as sac
import td3_continuous_action as td3
from conftest import OFF_POLICY, REPO, load, needs_cuda, parse, script_command, small_args, source
import forkserver
from rl_utils import CudaGraph, SeedEnvs, parse_args, per_seed, stack_seeds
from rl_utils.buffers import ReplayBuffer
import rl_utils.checkpoints as ckpt
import rl_utils.envs as env_layer
import rl_utils.seeds as seeds_module
from rl_utils.logs import Logs
from rl_utils.numerics import NonFiniteError
from rl_utils.run import Run
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


class FakeGraph:
    """torch.cuda.CUDAGraph's stand-in (recording needs a GPU): counts its replays."""

    made = []

    def __init__(self):
        self.replays = 0
        FakeGraph.made.append(self)

    def replay(self):
        self.replays += 1


class FakeStream:
    def wait_stream(self, other):
        pass


@pytest.fixture
def fake_cuda(monkeypatch):
    """CudaGraph's CUDA calls made stand-ins, so that its own warm-up, recording and replay logic runs on a CPU (the
    recorded graph runs the update once, at recording; a replay computes nothing)."""
    import contextlib

    FakeGraph.made = []
    monkeypatch.setattr(torch.cuda, "CUDAGraph", FakeGraph)
    monkeypatch.setattr(torch.cuda, "graph", lambda graph: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "Stream", FakeStream)
    monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "current_stream", FakeStream)
    return FakeGraph.made


def recorded_and_replayed(update, *inputs):
    """Calls update until its graph for these inputs is recorded and replayed once; returns that graph."""
    for _ in range(update.warmup + 1):  # eager warm-up calls, then the one that records and replays
        update(*inputs)
    (graph,) = FakeGraph.made
    assert graph.replays == 1
    return graph


TAU = 0.005  # a module-level number a helper of the update reads


def scaled_by_tau(x):
    return x * TAU


@dataclasses.dataclass(slots=True)
class SlotArgs:
    gamma: float = 0.99


CHANGES = {  # what a fork changes mid-run: the name the stop gives (None: the graph reads it anew, no stop)
    "lr": "optimizer.param_groups[0]['lr']",
    "args.tau": "args.tau",
    "a number": "scale",
    "a network bound anew": "net",
    "a tensor lr changed in place": None,
    "a module-level number a helper reads": "TAU",
    "a partial bound anew": "helper",
    "net.eval()": "net.training",
    "a field of slots args": "slot_args.gamma",
    "a NaN set to NaN": None,
    "a number in a dict": "config['beta']",
}


@pytest.mark.parametrize("change", list(CHANGES))
def test_a_graphed_update_stops_when_what_it_read_as_a_constant_changes(change, fake_cuda, monkeypatch):
    """A recorded graph keeps every number the update read while it was recorded: a learning-rate schedule on a float
    lr, a flag changed mid-run, a number main rebinds, a global a helper reads, a network put in eval mode would all be
    replayed as they were, without a word. The first replay after such a change stops, naming the value; a value
    the update takes as a tensor changed in place (a tensor lr, .fill_) is read anew and passes."""
    import math

    args, slot_args, config = td3.Args(), SlotArgs(), {"beta": 0.5}
    net = nn.Linear(3, 1)
    optimizer = torch.optim.Adam(net.parameters(), lr=torch.tensor(1e-3) if "tensor lr" in change else 1e-3)
    scale, nan = 2.0, math.nan
    helper = functools.partial(lambda x, factor: x * factor, 1.0)

    def update(batch, policy_step):
        loss = scaled_by_tau(helper(net(batch).sum()) * scale * args.tau * slot_args.gamma * config["beta"] + nan)
        return {"loss": loss, "lr": optimizer.param_groups[0]["lr"]}

    def rebind():
        nonlocal net, scale, nan, helper
        if change == "a network bound anew":
            net = nn.Linear(3, 1)
        elif change == "a number":
            scale = 3.0
        elif change == "a NaN set to NaN":
            nan = float("nan")
        elif change == "a partial bound anew":
            helper = functools.partial(helper.func, 2.0)

    graphed = CudaGraph(update)
    graph = recorded_and_replayed(graphed, torch.ones(2, 3), True)
    for _ in range(4):  # replays before the change: the watch is not only the first replay's
        graphed(torch.ones(2, 3), True)
    if change == "lr":
        optimizer.param_groups[0]["lr"] = 5e-4  # what a scheduler does
    elif change == "args.tau":
        args.tau = 0.01
    elif change == "a tensor lr changed in place":
        optimizer.param_groups[0]["lr"].fill_(5e-4)
    elif change == "a module-level number a helper reads":
        monkeypatch.setattr(sys.modules[__name__], "TAU", 0.01)
    elif change == "net.eval()":
        net.eval()
    elif change == "a field of slots args":
        slot_args.gamma = 0.9
    elif change == "a number in a dict":
        config["beta"] = 0.25
    else:
        rebind()
    calls = CudaGraph.CHECK_EVERY + 1  # a change is looked for every CHECK_EVERY replays
    if CHANGES[change] is None:
        for _ in range(calls):
            graphed(torch.ones(2, 3), True)
        assert graph.replays == 1 + 4 + calls
        return
    with pytest.raises(ValueError) as refused:
        for _ in range(calls):
            graphed(torch.ones(2, 3), True)
    message = str(refused.value)
    assert "\n" not in message and message.startswith(f"CudaGraph(update): `{CHANGES[change]}` ")
    bound_anew = change in ("a network bound anew", "a partial bound anew")
    advice = "load_state_dict(fresh.state_dict())" if bound_anew else "torch.tensor(lr, device=...)"
    assert advice in message and graph.replays < 1 + 4 + CudaGraph.CHECK_EVERY  # stopped within CHECK_EVERY replays


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


def td3_source() -> str:
    return open(os.path.join(REPO, "td3_continuous_action.py")).read()


def run_fork(tmp_path, edit, num_seeds=1, *extra):
    """A fork of TD3 (td3_continuous_action.py with `edit(source)` applied) run for 400 steps on Pendulum-v1."""
    (tmp_path / "fork_continuous_action.py").write_text(edit(td3_source()))
    flags = ["--env-id", "Pendulum-v1", "--total-timesteps", "400", "--learning-starts", "200", "--batch-size", "32"]
    flags += [
        "--eval-frequency",
        "400",
        "--eval-episodes",
        "1",
        "--num-seeds",
        str(num_seeds),
        "--run-name",
        "r{seed}",
        *extra,
    ]
    command = script_command("td3", *flags)
    command[1] = str(tmp_path / "fork_continuous_action.py")
    env = {**os.environ, "PYTHONPATH": REPO}
    return forkserver.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)


def assert_fork_stops(tmp_path, edit, error_start: str, num_seeds=1, *extra):
    """The fork (run_fork's) stops, the last line of its stderr starting `error_start`."""
    result = run_fork(tmp_path, edit, num_seeds, *extra)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1].startswith(error_start)


def line_of(fork: str, text: str) -> int:
    """The number of the fork's first line holding `text`."""
    return next(i for i, line in enumerate(fork.splitlines(), 1) if text in line)


def assert_stops_only_with_checkpoints(tmp_path, edit, error_start: str):
    """The fork stops (run_fork's, one seed) at a checkpoint of a run writing one every 150 steps, and runs to its end
    without checkpoints."""
    assert_fork_stops(tmp_path, edit, error_start, 1, "--checkpoint-frequency", "150")
    assert run_fork(tmp_path, edit, 1).returncode == 0


def assert_runs_with_checkpoints(tmp_path, edit):
    """The fork (run_fork's, one seed) runs to its end writing a checkpoint every 150 steps."""
    result = run_fork(tmp_path, edit, 1, "--checkpoint-frequency", "150")
    assert result.returncode == 0, result.stderr


def assert_one_seed_runs_and_two_stop(tmp_path, edit, error_start: str):
    """The fork runs to its end with one seed and stops with two, its last line of stderr starting `error_start`."""
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    assert run_fork(one, edit, 1).returncode == 0
    assert_fork_stops(two, edit, error_start, 2)


@needs_cuda
def test_a_fork_with_a_float_learning_rate_schedule_stops_under_cudagraphs(tmp_path):
    """A fork of TD3 that halves its critic's learning rate at step 300, as a scheduler would (a float in the
    optimizer's param group): its recorded update would go on with the old rate. Under --cudagraphs the first replay
    after the change stops, naming it."""
    anchor = "        run.log_episodes(infos, global_step)\n"
    schedule = "        if global_step == 300:\n            q_optimizer.param_groups[0]['lr'] = 1.5e-4\n"
    result = run_fork(tmp_path, lambda source: source.replace(anchor, anchor + schedule), 1, "--cudagraphs")
    assert result.returncode != 0
    assert (
        "CudaGraph(update): `q_optimizer.param_groups[0]['lr']` was 0.0003 when the graph was recorded and is "
        in (result.stderr.strip().splitlines()[-1])
    )


def test_a_network_main_holds_but_does_not_checkpoint_is_refused_at_the_start(tmp_path):
    """A fork that adds a network (a second target critic, say) but not to run.start's nets would resume it from its
    initial weights: refused before the first step."""
    anchor = "    nets = {"
    result = run_fork(tmp_path, lambda s: s.replace(anchor, "    extra_critic = QEnsemble(obs_dim, action_dim)\n" + anchor, 1))
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: `extra_critic` is not in run.start's nets: a checkpoint would not hold it; add it there"
    )


def test_random_actions_drawn_as_cleanrl_draws_them_are_refused_in_one_line(tmp_path):
    """CleanRL's habit, `envs.action_space.sample()`, gives one env's action [action_dim] (SeedEnvs.action_space is
    one env's): stepped, a DeepMind Control env would broadcast a number to every actuator. Refused at the step."""
    edit = lambda source: source.replace("envs.sample_actions()", "envs.action_space.sample()")  # noqa: E731
    step_line = next(k for k, line in enumerate(edit(td3_source()).splitlines(), 1) if "envs.step(actions)" in line)
    result = run_fork(tmp_path, edit)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: SeedEnvs.step: actions have shape [1], not [num_seeds, action_dim] = [1, 1]: one row per seed's env "
        f"(random ones: envs.sample_actions(); envs.action_space is one env's) (at fork_continuous_action.py:{step_line})"
    )


def test_random_actions_drawn_one_per_seed_from_envs_action_space_are_refused_with_several_seeds():
    """`np.array([envs.action_space.sample() for _ in run.seeds])` has the right shape, but every seed's draw would
    come from one generator, and seed k's env's own would never move (a seed's random phase not its solo run's)."""
    envs = SeedEnvs("Pendulum-v1", [1, 2])
    with pytest.raises(RuntimeError, match=r"^envs.action_space.sample\(\) with 2 seeds: .* envs.sample_actions\(\)"):
        np.array([envs.action_space.sample() for _ in range(2)])
    assert envs.action_space == envs.envs[0].action_space and envs.sample_actions().shape == (2, 1)
    one = SeedEnvs("Pendulum-v1", [1])
    assert one.action_space.sample().shape == (1,)  # one seed: its env's own space and generator
    envs.close(), one.close()


@pytest.mark.parametrize("num_seeds", [1, 2])
def test_exploration_noise_drawn_from_numpy_in_the_loop_is_refused_with_several_seeds(tmp_path, num_seeds):
    """A fork of TD3 that adds NumPy noise of one seed's shape to the actor's actions in the loop, as TD3's original
    code does: one seed, the noise is that seed's own and the run ends; two, every seed would get the same noise, and
    the run stops within 100 steps of the first draw (step 200, the end of the random actions), naming the fix."""
    line = (
        "            actions = per_seed(noisy_action)(to_device(obs, device), actor, args.exploration_noise).cpu().numpy()\n"
    )
    noised = (
        "            actions = per_seed(actor)(to_device(obs, device)).detach().cpu().numpy()\n"
        "            actions += np.random.normal(0, 0.1, size=envs.action_space.shape)\n"
        "            actions = actions.clip(envs.action_space.low, envs.action_space.high).astype(np.float32)\n"
    )

    def edit(source):
        assert line in source
        return source.replace(line, noised, 1)

    result = run_fork(tmp_path, edit, num_seeds)
    if num_seeds == 1:
        assert result.returncode == 0, result.stderr[-2000:]
        return
    assert result.returncode == 1
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith(
        "error: SeedEnvs.step with 2 seeds: Python's or NumPy's global random generator drew in the last 100 steps (in "
        "the loop, or code it calls): with several seeds it is the process's stream, not any seed's, and a draw of one "
        "seed's shape (np.random.normal(0, s, size=envs.action_space.shape)) gives every seed the same numbers"
    ), last
    assert "draw with torch inside a per-seed function, as noisy_action does" in last


def test_the_global_generators_are_watched_between_the_steps_of_several_seeds_only():
    """SeedEnvs with two seeds: 300 steps without a draw of the loop's own run; a draw of NumPy's or Python's global
    generator between two steps stops within DRAWS_EVERY steps; with one seed the global generators are its own."""
    for draw in (lambda: np.random.normal(size=1), lambda: random.random()):
        envs = SeedEnvs("Pendulum-v1", [1, 2])
        envs.reset()
        for _ in range(300):
            envs.step(envs.sample_actions())
        steps = 0
        with pytest.raises(RuntimeError, match="^SeedEnvs.step with 2 seeds: Python's or NumPy's global random generator"):
            while steps < 200:
                draw()
                envs.step(envs.sample_actions())
                steps += 1
        assert steps == env_layer.DRAWS_EVERY - 1  # the look at the 400th step
        envs.close()
    envs = SeedEnvs("Pendulum-v1", [1])
    envs.reset()
    for _ in range(300):
        np.random.normal()
        envs.step(envs.sample_actions())
    envs.close()


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


def scaled_by_item(x, net):
    return net(x).mean() * x.abs().max().item()  # a value read into Python


def clipped_by_if(x, net):
    y = net(x).mean()
    return y if y > 0 else -y  # an `if` on a tensor


def noised_with_numpy(x, net):
    return net(x).mean() + float(np.random.normal())  # a draw from NumPy's generator


def noised_with_random(x, net):
    return net(x).mean() * random.uniform(0.9, 1.1)  # a draw from Python's generator


@pytest.mark.parametrize("fn", [scaled_by_item, clipped_by_if, noised_with_numpy, noised_with_random])
def test_what_a_vmap_cannot_run_per_seed_runs_for_one_seed_and_stops_in_one_line_for_several(fn):
    """A one-seed function that reads a value into Python, or draws from Python's or NumPy's generator, runs as
    written with one seed; with several, vmap could not run the first per seed and would run the draw once, shared by
    every seed, without a word: both stop, in one line that names the function and what to write instead."""
    x = torch.randn(1, 8, 3)
    np.random.seed(0)
    random.seed(0)
    alone = per_seed(fn)(x, built([4]))
    np.random.seed(0)
    random.seed(0)
    assert torch.equal(alone, fn(x[0], built([4])).unsqueeze(0))  # as written
    with pytest.raises(RuntimeError) as refused:
        per_seed(fn)(torch.randn(3, 8, 3), built([4, 5, 6]))
    message = str(refused.value)
    assert "\n" not in message and message.startswith(f"per_seed({fn.__name__}) with 3 seeds")
    assert "torch.randn_like" in message
    if fn in (noised_with_numpy, noised_with_random):
        assert "one draw the seeds would share" in message
    else:
        assert "cannot read a tensor's value into Python" in message


NUMPY_GENERATOR = np.random.default_rng(0)
DRAW = np.random.default_rng(1).normal  # a method of a generator


def noised_with_a_global_generator(x, net):
    return net(x).mean() + float(NUMPY_GENERATOR.normal())  # a module's own NumPy Generator


def noised_with_a_generators_method(x, net):
    return net(x).mean() + float(DRAW())


def noised_with(generator):
    def noised(x, net):
        return net(x).mean() + float(generator.random())  # a generator the function closes over

    return noised


class OUNoise:  # a helper object of the fork's own, holding its generator
    def __init__(self):
        self.rng, self.state = np.random.default_rng(3), 0.0

    def sample(self):
        self.state = 0.85 * self.state + 0.2 * self.rng.normal()
        return self.state


def noised_by(noises):
    def noised(x, net):
        return net(x).mean() + float(noises[0].sample())  # an OU noise in a list

    return noised


class NoisyLinear(nn.Linear):  # a network holding its generator
    def __init__(self, *shape):
        super().__init__(*shape)
        self.rng = random.Random(4)

    def forward(self, x):
        return super().forward(x) * self.rng.uniform(0.9, 1.1)


@pytest.mark.parametrize(
    "fn, name",
    [
        (noised_with_a_global_generator, "NUMPY_GENERATOR"),
        (noised_with_a_generators_method, "DRAW"),
        (noised_with(np.random.RandomState(1)), "generator"),
        (functools.partial(noised_with(random.Random(2))), "generator"),
        (noised_by([OUNoise()]), "noises[0].rng"),
        (None, "NoisyLinear.rng"),
    ],
    ids=[
        "global Generator",
        "a Generator's method",
        "closed-over RandomState",
        "partial over a random.Random",
        "an OU noise's generator",
        "a network's generator",
    ],
)
def test_a_generator_of_a_forks_own_in_a_per_seed_function_runs_for_one_seed_and_stops_for_several(fn, name):
    """A per-seed function drawing from a generator of the fork's own (np.random.default_rng(), RandomState,
    random.Random): named as a global, closed over, behind a partial, as a method, held by an object of the fork's
    own in a list, or by a network. With one seed it is that seed's own draw; with several, one draw every seed would
    share: it stops in one line naming the generator. A SystemRandom, which has no state to watch, is passed over."""
    if fn is None:
        one, three = NoisyLinear(3, 1), stack_seeds(lambda: [NoisyLinear(3, 1)], [1, 2, 3], torch.device("cpu"))[0]
        assert per_seed(one)(torch.randn(1, 8, 3)).shape == (1, 8, 1)
        call = lambda: per_seed(three)(torch.randn(3, 8, 3))  # noqa: E731
    else:
        assert per_seed(fn)(torch.randn(1, 8, 3), built([4])).shape == (1,)
        call = lambda: per_seed(fn)(torch.randn(3, 8, 3), built([4, 5, 6]))  # noqa: E731
    with pytest.raises(RuntimeError) as refused:
        call()
    message = str(refused.value)
    assert "\n" not in message and message.startswith(
        f"per_seed({seeds_module.name_of(fn if fn else three)}) with 3 seeds drew from `{name}`, a random generator of "
        "its own, which a vmap over the seeds runs once"
    ), message
    entropy = random.SystemRandom()
    assert per_seed(lambda x, net: net(x).mean() * (entropy is not None))(torch.randn(3, 8, 3), built([4, 5, 6])).shape == (3,)


def test_torch_draws_in_a_per_seed_function_are_each_seeds_own_and_pass_the_watch():
    def noised(x, net):
        return net(x).squeeze(-1) + torch.randn_like(x[..., 0]) + torch.rand(x.shape[:-1]) + torch.randperm(8)

    out = per_seed(noised)(torch.zeros(3, 8, 3), built([4, 5, 6]))
    assert out.shape == (3, 8) and not torch.equal(out[0] - out[0].mean(), out[1] - out[1].mean())


def two_layers():
    return [nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 1))]


def two_steps(parameters, max_norm):
    """clip_grad_norm_ as PyTorch's two public parts: the norm, then the clipping."""
    parameters = list(parameters)
    norm = nn.utils.get_total_norm([p.grad for p in parameters])
    nn.utils.clip_grads_with_norm_(parameters, max_norm, norm)
    return norm


@pytest.mark.parametrize("style", ["clip_grad_norm_", "two steps"])
def test_clip_grad_norm_clips_each_seed_by_its_own_norm(style):
    """A fork's torch.nn.utils.clip_grad_norm_ (or its two public parts, get_total_norm and clip_grads_with_norm_)
    in a process of three seeds clips each seed's gradients by that seed's norm, as the seed's single-seed run would,
    and returns the seeds' norms; one seed's gradients are PyTorch's own computation, bit for bit."""
    clip = {"clip_grad_norm_": nn.utils.clip_grad_norm_, "two steps": two_steps}[style]
    seeds = [4, 5, 6]
    torch.manual_seed(4)
    stacked = stack_seeds(two_layers, seeds, torch.device("cpu"))[0]
    alone = []
    for seed in seeds:
        torch.manual_seed(seed)
        alone.append(two_layers()[0])
    x = torch.randn(3, 16, 3) * torch.tensor([1.0, 10.0, 100.0]).view(3, 1, 1)  # norms far apart: each seed its own
    per_seed(lambda x, net: net(x).pow(2).mean())(x, stacked).sum().backward()
    norms = clip(stacked.parameters(), 1.0)
    assert norms.shape == (3,) and norms.min() < 1.0 < norms.max()  # one seed left as it is, the others clipped
    for k, net in enumerate(alone):
        net(x[k]).pow(2).mean().backward()
        plain = [p.grad.clone() for p in net.parameters()]
        norm = seeds_module.torch_total_norm(plain)
        torch.testing.assert_close(norms[k], norm)
        seeds_module.torch_clip_grads_with_norm(list(net.parameters()), 1.0, norm)
        for p, q in zip(stacked.parameters(), net.parameters()):
            torch.testing.assert_close(p.grad[k], q.grad)
    one = two_layers()[0]
    one(x[0]).pow(2).mean().backward()
    twin = [p.grad.clone() for p in one.parameters()]
    norm = clip(one.parameters(), 0.5)
    expected = seeds_module.torch_total_norm(twin)
    assert torch.equal(norm, expected)
    for p, g in zip(one.parameters(), twin):
        assert torch.equal(p.grad, g * torch.clamp(0.5 / (expected + 1e-6), max=1.0))


def test_a_copy_of_a_stacked_network_and_the_inf_norm_are_clipped_per_seed_too():
    """A fork's deepcopy of a stacked network (a second target, say) is clipped per seed as the original; so is the
    largest-entry norm, norm_type='inf'."""
    import copy

    stacked = copy.deepcopy(stack_seeds(two_layers, [4, 5, 6], torch.device("cpu"))[0])
    x = torch.randn(3, 16, 3) * torch.tensor([1.0, 10.0, 100.0]).view(3, 1, 1)
    per_seed(lambda x, net: net(x).pow(2).mean())(x, stacked).sum().backward()
    largest = torch.stack([torch.cat([p.grad[k].flatten() for p in stacked.parameters()]).abs().max() for k in range(3)])
    norms = nn.utils.clip_grad_norm_(stacked.parameters(), 0.1, norm_type="inf")
    torch.testing.assert_close(norms, largest)
    for k in range(3):
        after = torch.cat([p.grad[k].flatten() for p in stacked.parameters()]).abs().max()
        torch.testing.assert_close(after, torch.clamp(largest[k], max=0.1), rtol=1e-5, atol=0)


def test_clip_grad_norm_over_stacked_and_plain_parameters_together_is_refused_in_one_line():
    stacked = stack_seeds(two_layers, [4, 5], torch.device("cpu"))[0]
    plain = nn.Linear(3, 1)
    per_seed(lambda x, net: net(x).sum())(torch.randn(2, 5, 3), stacked).sum().backward()
    plain(torch.randn(5, 3)).sum().backward()
    with pytest.raises(RuntimeError) as refused:
        nn.utils.clip_grad_norm_([*stacked.parameters(), *plain.parameters()], 1.0)
    assert "\n" not in str(refused.value) and "in a call of their own" in str(refused.value)


def test_a_reset_by_nn_init_initialises_each_seed_as_a_one_seed_tensor():
    """A fork that resets a layer mid-run with nn.Linear's reset_parameters() or torch.nn.init (as primacy-bias
    resets do): with three seeds stacked, each seed's slice is initialised as a one-seed weight would be, its fans
    those of [out, in] (not [3, out, in], which would shrink kaiming's bound by sqrt(7)), orthogonal_ per seed; also
    through .data and on a deepcopy of the network. A part of the stacked weight that is no seed's is refused."""
    import copy
    import math

    torch.manual_seed(0)
    seeds = [4, 5, 6]
    layer = stack_seeds(lambda: [nn.Linear(5, 7)], seeds, torch.device("cpu"))[0]
    before = layer.weight
    bound = 5**-0.5  # kaiming_uniform_(a=sqrt(5)): |w| <= 1/sqrt(fan_in); the bias too
    for reset in (
        layer.reset_parameters,
        lambda: nn.init.kaiming_uniform_(layer.weight.data, a=math.sqrt(5)),
        lambda: copy.deepcopy(layer).reset_parameters(),
    ):
        reset()
        assert layer.weight is before
    copied = copy.deepcopy(layer)
    copied.reset_parameters()
    for net in (layer, copied):
        for k in range(3):  # each seed its own draw, spread as a one-seed layer's
            assert 0.8 * bound < net.weight[k].abs().max() <= bound
        assert net.bias.abs().max() <= bound and net.bias.abs().max() > 0.6 * bound
    assert not torch.equal(layer.weight[0], layer.weight[1])
    nn.init.xavier_uniform_(layer.weight)
    assert 0.8 * (6 / (5 + 7)) ** 0.5 < layer.weight.abs().max() <= (6 / (5 + 7)) ** 0.5
    with pytest.raises(RuntimeError, match=r"nn.init on a part \[3, 7, 3\] of a parameter stacked for 3 seeds"):
        nn.init.kaiming_uniform_(layer.weight.data[:, :, :3])
    nn.init.orthogonal_(layer.weight)
    for k in range(3):
        torch.testing.assert_close(layer.weight[k].T @ layer.weight[k], torch.eye(5), atol=1e-5, rtol=0)
    one = stack_seeds(lambda: [nn.Linear(5, 7)], [4], torch.device("cpu"))[0]
    torch.manual_seed(0)
    nn.init.orthogonal_(one.weight)
    torch.manual_seed(0)
    plain = torch.empty(7, 5)
    torch.nn.init.orthogonal_(plain)
    assert torch.equal(one.weight.detach(), plain)  # one seed: PyTorch's own initialisation


@pytest.mark.slow
@pytest.mark.parametrize("script", OFF_POLICY)
def test_the_scripts_own_graphed_updates_pass_the_watch(script, fake_cuda, tmp_path, monkeypatch):
    """Each off-policy script's own update under --cudagraphs (CUDA stand-ins, on a CPU) replays to the end of a run
    without the watch stopping it: nothing it reads changes between replays (OPARL's resets and SAC's alpha are made
    in place), so the watch stops a fork's change and no run of the scripts as they are."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    extra = {"reset_frequency": 50} if "reset_frequency" in {f.name for f in dataclasses.fields(module.Args)} else {}
    args = small_args(module, env_id="Pendulum-v1", total_timesteps=600, learning_starts=300, cudagraphs=True, **extra)
    module.main(args)
    assert fake_cuda and sum(graph.replays for graph in fake_cuda) > 2 * CudaGraph.CHECK_EVERY


# what the forker's walk of this page met (docs/forking.md, "Caught since"): each a fork's plain-PyTorch change
SCHEDULER_AT = "    rb = ReplayBuffer("
STEP_AT = "        run.end_step(global_step)  # training speed, progress bar, checkpoints\n"
SCHEDULERS = {
    "LambdaLR": "torch.optim.lr_scheduler.LambdaLR(q_optimizer, lambda i: 1 - i / 1000)",
    "ReduceLROnPlateau": "torch.optim.lr_scheduler.ReduceLROnPlateau(q_optimizer)",  # wraps no optimizer step
}


def with_scheduler(source, scheduler, given):
    """TD3 with a learning-rate schedule on its critics, stepped after each update (`given`: in run.start's parts), that
    exits at step $FORK_STOP_AT as if killed."""
    step = "q_scheduler.step(0.0)" if "Plateau" in scheduler else "q_scheduler.step()"
    fork = source.replace(SCHEDULER_AT, f"    q_scheduler = {scheduler}\n" + SCHEDULER_AT, 1)
    fork = fork.replace(STEP_AT, f"        if global_step >= args.learning_starts:\n            {step}\n" + STEP_AT)
    loop = "    for global_step in range(run.start_step, args.total_timesteps):\n"
    kill = "        if global_step == int(os.environ.get('FORK_STOP_AT', -2)) + 1:\n            os._exit(9)  # a kill\n"
    fork = fork.replace(loop, loop + kill, 1)  # after step FORK_STOP_AT ended (a kill after run.end_step)
    if given:
        fork = fork.replace("buffer=rb)", "buffer=rb, q_scheduler=q_scheduler)")
    assert fork.count("q_scheduler") == (4 if given else 2) and "os._exit" in fork
    return fork if "\nimport os\n" in fork else fork.replace("import random\n", "import os\nimport random\n")


@pytest.mark.parametrize("scheduler", list(SCHEDULERS))
def test_a_learning_rate_scheduler_the_checkpoints_would_not_hold_is_refused_at_the_start(scheduler, tmp_path):
    """A scheduler's place in its schedule is state: left out of run.start's parts, --resume would start the schedule
    again and train on other learning rates than the uninterrupted run, silently. A run that writes checkpoints is
    refused before its first step."""
    fork = functools.partial(with_scheduler, scheduler=SCHEDULERS[scheduler], given=False)
    assert run_fork(tmp_path, fork).returncode == 0  # without checkpoints (the scripts' default) there is no resume
    result = run_fork(tmp_path, fork, 1, "--checkpoint-frequency", "200")
    assert result.returncode == 1
    line = result.stderr.strip().splitlines()[-1]
    if scheduler == "LambdaLR":  # found by name, as the optimizer's: both say the fix
        assert line.startswith("error: `q_scheduler`, a learning-rate scheduler, is not in run.start's parts")
    assert "--resume would start it again" in line and "q_scheduler=q_scheduler" in line


def test_a_learning_rate_that_follows_a_loss_is_refused_at_the_start_with_several_seeds(tmp_path):
    """ReduceLROnPlateau follows one number; one optimizer steps every seed's weights. With two seeds it would set one
    learning rate for both, following one seed's loss or their sum: refused before the first step (with one seed the
    schedule runs, above)."""
    fork = functools.partial(with_scheduler, scheduler=SCHEDULERS["ReduceLROnPlateau"], given=True)
    result = run_fork(tmp_path, fork, 2)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: `q_scheduler` (ReduceLROnPlateau) follows one number, and its optimizer steps every seed's weights: "
        "with 2 seeds it would set one learning rate for all of them; train one seed per process (--num-seeds 1)"
    )


def test_a_scheduler_found_by_the_optimizer_step_it_wraps_and_one_made_of_others():
    """A scheduler main does not hold by name (made in a helper) is found by the optimizer step it wraps; one made
    of others (SequentialLR) holds theirs, which are not refused beside it."""
    from rl_utils.run import Run

    def checked(parts, **names):
        run = Run.__new__(Run)
        run.args, run.parts = dataclasses.replace(td3.Args(), checkpoint_frequency=100), parts
        run.optimizers, run.caller = {"q_optimizer": optimizer}, types.SimpleNamespace(f_locals=names, f_globals=globals())
        run.check_state_held()

    optimizer = torch.optim.Adam([nn.Parameter(torch.zeros(2))], lr=1e-3)
    checked({}, Critic=nn.Linear, opt_class=torch.optim.Adam)  # no scheduler; classes hold no state
    warmup = torch.optim.lr_scheduler.LinearLR(optimizer, 0.1, total_iters=10)
    cosine = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, 100)
    with pytest.raises(SystemExit, match=r"`q_optimizer` has a learning-rate scheduler that run.start's parts do not"):
        checked({})
    schedule = torch.optim.lr_scheduler.SequentialLR(optimizer, [warmup, cosine], milestones=[10])
    checked({"q_scheduler": schedule}, warmup=warmup, cosine=cosine, q_scheduler=schedule)
    with pytest.raises(SystemExit, match=r"`cosine`, a learning-rate scheduler, is not in run.start's parts"):
        checked({"warmup": warmup}, warmup=warmup, cosine=cosine)


@pytest.mark.slow
def test_a_scheduler_given_to_run_start_resumes_where_its_schedule_was(tmp_path):
    """Two seeds with a LambdaLR on their critics' optimizer and exploration noise from a generator of the fork's own
    (both given to run.start), killed after the checkpoint at step 300 and resumed: the schedule, the learning rate,
    the generator and every weight end as in the uninterrupted process."""

    def fork(source):
        scheduled = with_scheduler(source, scheduler=SCHEDULERS["LambdaLR"], given=True)
        return with_generator(scheduled, parts=", noise_rng=noise_rng")

    flags = ["--checkpoint-frequency", "300"]
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    for folder in (whole, killed):
        folder.mkdir()
    assert run_fork(whole, fork, 2, *flags).returncode == 0
    os.environ["FORK_STOP_AT"] = "350"
    try:
        assert run_fork(killed, fork, 2, *flags).returncode == 9
    finally:
        del os.environ["FORK_STOP_AT"]
    assert torch.load(killed / "runs" / "r2" / "checkpoint.pt", weights_only=True)["global_step"] == 300
    resumed = run_fork(killed, fork, 2, *flags, "--resume", "runs/r1")
    assert resumed.returncode == 0, resumed.stderr
    for seed in ("r1", "r2"):
        a, b = (torch.load(folder / "runs" / seed / "checkpoint.pt", weights_only=True) for folder in (whole, killed))
        assert a["global_step"] == b["global_step"] == 400
        assert a["q_scheduler"]["last_epoch"] == b["q_scheduler"]["last_epoch"] == 200  # a step per update
        assert a["noise_rng"] == b["noise_rng"]
        assert (
            a["optimizers"]["q_optimizer"]["param_groups"][0]["lr"] == b["optimizers"]["q_optimizer"]["param_groups"][0]["lr"]
        )
        for net in ("qf", "actor"):
            for name, tensor in a["nets"][net].items():
                assert torch.equal(tensor, b["nets"][net][name]), (seed, net, name)


@pytest.mark.parametrize("num_seeds", [1, 2])
@pytest.mark.parametrize(
    "stored, refusal",
    [
        (
            "rb.add(obs, next_obs, actions, rewards, terminations)",
            "ReplayBuffer.add: next_obs's row for seed index 0 is the next episode's first observation (envs.step's "
            "next_obs, or a copy of it), where the episode ended at this step, stored as not terminated: its target "
            'would bootstrap from it; store the observation the step led to, infos["real_next_obs"]',
        ),
        (
            'rb.add(obs, infos["real_next_obs"], actions, rewards, np.logical_or(terminations, truncations))',
            "ReplayBuffer.add: terminations is 1 for seed index 0, whose episode its time limit cut (truncated, not "
            "terminated): its target must bootstrap from the next observation; store the terminations envs.step "
            "returned, not terminations | truncations (a fork that means a time limit to end its episodes sets "
            "rb.time_limits_end_episodes = True)",
        ),
        (
            "real_next_obs = next_obs.copy()\n"
            "for idx, trunc in enumerate(truncations):\n"
            "    if trunc:\n"
            '        real_next_obs[idx] = infos["real_next_obs"][idx]\n'
            "rb.add(obs, real_next_obs, actions, rewards, terminations | truncations)",
            "ReplayBuffer.add: terminations is 1 for seed index 0, whose episode its time limit cut (truncated, not "
            "terminated): its target must bootstrap from the next observation; store the terminations envs.step "
            "returned, not terminations | truncations (a fork that means a time limit to end its episodes sets "
            "rb.time_limits_end_episodes = True)",
        ),
    ],
    ids=["next_obs", "dones", "fixed-up copy and dones"],
)
def test_a_fork_storing_the_reset_observation_or_truncations_as_ends_stops_at_the_first_episode_end(
    tmp_path, stored, refusal, num_seeds
):
    """CleanRL-era slips: a fork of TD3 that stores the next_obs envs.step returned (where an episode ended, the next
    episode's first observation) or `terminations | truncations` (no bootstrap where Pendulum's 200-step time limit
    cuts an episode, as every DeepMind Control episode is cut), with the observations the step led to or with
    CleanRL's older fix-up (a copy of next_obs, the final observations put back), would train on wrong targets; it
    stops at the first episode's end, step 199, naming the fix and the fork's line."""
    line = '        rb.add(obs, infos["real_next_obs"], actions, rewards, terminations)'

    def edit(source):
        assert line in source
        return source.replace(line, "".join("        " + part for part in stored.splitlines(True)), 1)

    result = run_fork(tmp_path, edit, num_seeds)
    assert result.returncode == 1
    last = result.stderr.strip().splitlines()[-1]
    assert re.fullmatch(re.escape(f"error: {refusal} (at fork_continuous_action.py:") + r"\d+\)", last), last


def cleanrl_fix_up(next_obs, truncations, real_next_obs):
    """CleanRL's own fix of an autoreset step: a copy of next_obs with the rows a time limit cut put back."""
    fixed = next_obs.copy()
    for idx, trunc in enumerate(truncations):
        if trunc:
            fixed[idx] = real_next_obs[idx]
    return fixed


def two_seed_envs_and_buffer(env_id, capacity):
    envs = SeedEnvs(env_id, [1, 2])
    return envs, envs.reset(), ReplayBuffer(capacity, envs.obs_dim, envs.action_dim, 2, torch.device("cpu"))


def test_what_is_stored_is_checked_in_copies_of_what_envs_step_returns():
    """Where an episode ended, next_obs holds the next episode's first observation: refused in any array that holds
    it (a copy, np.array); CleanRL's fix (next_obs.copy() with the final observations put back) stores the observations
    the step led to. The time limit's rows are marked on next_obs and real_next_obs, and on their copies: stored with
    terminations | truncations, refused; np.asarray (the escape for a fork that means it) drops the mark."""
    envs, obs, rb = two_seed_envs_and_buffer("Pendulum-v1", 300)
    for step in range(200):
        next_obs, rewards, terminations, truncations, infos = envs.step(envs.sample_actions())
        real = infos["real_next_obs"]
        assert next_obs.truncated.tolist() == real.truncated.tolist() == [step == 199] * 2
        assert isinstance(next_obs, np.ndarray) and repr(next_obs).startswith("array(")
        if step == 199:
            assert not np.array_equal(next_obs, real)  # the next episode's first observations
            fixed = cleanrl_fix_up(next_obs, truncations, real)
            rb.add(obs, fixed, envs.sample_actions(), rewards, terminations)
            assert torch.equal(rb.storage[:, step, -envs.obs_dim - 2 : -2], torch.from_numpy(np.asarray(real, np.float32)))
            for stored in (next_obs, next_obs.copy(), np.array(next_obs), next_obs.astype(np.float64), next_obs.tolist()):
                with pytest.raises(ValueError, match="^ReplayBuffer.add: next_obs's row for seed index 0 is the next "):
                    rb.add(obs, stored, envs.sample_actions(), rewards, terminations)
            for stored in (real, fixed, real.copy()):
                with pytest.raises(ValueError, match="^ReplayBuffer.add: terminations is 1 for seed index 0, whose episode"):
                    rb.add(obs, stored, envs.sample_actions(), rewards, terminations | truncations)
            rb.add(obs, np.asarray(real), envs.sample_actions(), rewards, terminations | truncations)  # unmarked: stored
        else:
            rb.add(obs, next_obs, envs.sample_actions(), rewards, terminations)  # no episode ended: the same rows
        obs = next_obs
    assert rb.size == 201 and rb.storage[:, 200, -1].tolist() == [1.0, 1.0]
    assert type(next_obs.max()) is np.float32 and type(next_obs * 2) is np.ndarray  # plain results, as from any array
    assert next_obs[:1].truncated is None  # a slice of other rows carries no mark
    next_obs, *_ = envs.step(envs.sample_actions())
    rb.add(obs, next_obs.copy(), envs.sample_actions(), rewards, terminations)  # the next step: no episode ended
    envs.close()


def test_where_one_seeds_episode_ends_alone_a_termination_stores_any_next_obs_and_a_time_limit_is_named():
    """Hopper-v4, seeds 1 and 2, random actions: the second seed's hopper falls first, alone (step 12). A terminated
    row's target reads no next observation: the next_obs envs.step returned, and CleanRL's fix-up (a copy, the rows a
    time limit cut put back), are stored; stored as not terminated, that row is refused, by its index. Pendulum with
    the first seed's episode begun a step late: the second seed's time limit comes alone, and is named."""
    envs, obs, rb = two_seed_envs_and_buffer("Hopper-v4", 100)
    for step in range(100):
        next_obs, rewards, terminations, truncations, infos = envs.step(envs.sample_actions())
        if terminations.any():
            break
        rb.add(obs, next_obs, envs.sample_actions(), rewards, terminations)
        obs = next_obs
    assert terminations.tolist() == [False, True] and not truncations.any(), (step, terminations)
    fixed = cleanrl_fix_up(next_obs, truncations, infos["real_next_obs"])
    for stored in (next_obs, fixed, infos["real_next_obs"]):
        rb.add(obs, stored, envs.sample_actions(), rewards, terminations)
    with pytest.raises(ValueError, match="^ReplayBuffer.add: next_obs's row for seed index 1 is the next episode's first"):
        rb.add(obs, next_obs, envs.sample_actions(), rewards, np.zeros(2))
    assert rb.size == step + 3
    envs.close()
    envs, obs, rb = two_seed_envs_and_buffer("Pendulum-v1", 300)
    envs.step(envs.sample_actions())
    envs.envs[0].reset(seed=1)  # the first seed's episode begins again, a step after the second's
    for step in range(199):
        next_obs, rewards, terminations, truncations, infos = envs.step(envs.sample_actions())
    assert truncations.tolist() == [False, True]
    with pytest.raises(ValueError, match="^ReplayBuffer.add: next_obs's row for seed index 1 is the next episode's first"):
        rb.add(obs, next_obs, envs.sample_actions(), rewards, terminations)
    with pytest.raises(ValueError, match="^ReplayBuffer.add: terminations is 1 for seed index 1, whose episode its time"):
        rb.add(obs, infos["real_next_obs"], envs.sample_actions(), rewards, terminations | truncations)
    rb.add(obs, infos["real_next_obs"], envs.sample_actions(), rewards, terminations)
    envs.close()


@pytest.mark.parametrize(
    "logged, what",
    [("qf_a_values.max()", "a tensor of shape []"), ("qf_a_values.max().item()", "a number (float)")],
    ids=["0-d tensor", "item"],
)
def test_a_value_over_every_seed_logged_as_one_is_refused_with_several_seeds(tmp_path, logged, what):
    """A fork that logs the largest Q-value over every seed's values, as a 0-d tensor or read with .item(), would log
    the same number in every seed's run; with one seed it is that seed's own. Several seeds: refused when it is first
    logged."""
    anchor = '            logs = {"losses/qf_values":'

    def edit(source):
        return source.replace(anchor, f'            logs = {{"losses/qf_max": {logged}, "losses/qf_values":', 1)

    assert_one_seed_runs_and_two_stop(
        tmp_path, edit, f"error: run.log: `losses/qf_max` is {what} for 2 seeds: log one value per seed, a tensor [2]"
    )


def test_run_log_takes_one_value_per_seed_and_refuses_one_for_all_with_several_seeds():
    """With several seeds each seed's run gets its own entry of a tensor, an array or a list [num_seeds] (a value the
    seeds share given as [value] * num_seeds); a Python or NumPy number or a tensor of another size is refused before
    anything is written. With one seed a number is that seed's."""

    class Writer:
        def __init__(self):
            self.scalars = []

        def add_scalar(self, tag, value, step):
            self.scalars.append((tag, value, step))

    def logs(num_seeds):
        logs = Logs.__new__(Logs)
        logs.writers = [Writer() for _ in range(num_seeds)]
        return logs

    two = logs(2)
    two.log({"a": torch.tensor([1.0, 2.0]), "b": np.array([3.0, 4.0]), "c": [0.5] * 2}, 7)
    assert [w.scalars for w in two.writers] == [
        [("a", 1.0, 7), ("b", 3.0, 7), ("c", 0.5, 7)],
        [("a", 2.0, 7), ("b", 4.0, 7), ("c", 0.5, 7)],
    ]
    for value, what in [
        (1.5, "a number (float)"),
        (np.float32(1.5), "a number (float32)"),
        (3, "a number (int)"),
        (torch.tensor(1.5), "a tensor of shape []"),
        (torch.ones(3), "a tensor of shape [3]"),
        (np.ones((2, 2)), "an array of shape [2, 2]"),
    ]:
        fresh = logs(2)
        with pytest.raises(ValueError, match=re.escape(f"run.log: `b` is {what} for 2 seeds: log one value per seed")):
            fresh.log({"a": torch.ones(2), "b": value}, 7)
        assert all(w.scalars == [] for w in fresh.writers)
    one = logs(1)
    one.log({"a": 1.5, "b": torch.tensor(2.5)}, 3)
    assert one.writers[0].scalars == [("a", 1.5, 3), ("b", 2.5, 3)]


def test_a_refusal_in_a_forks_per_seed_function_is_one_line_on_the_command_line(tmp_path, monkeypatch):
    """`.item()` in TD3's critic loss, two seeds: the run stops with the refusal's one line, which names the fork's
    line in place of the traceback; RL_UTILS_TRACEBACK=1 gives the traceback."""
    anchor = "    qf_a_values = qf(batch.observations, batch.actions)\n"

    def edit(source):
        return source.replace(anchor, anchor + "    float(qf_a_values.max().item())\n", 1)

    line = edit(td3_source()).splitlines().index("    float(qf_a_values.max().item())")
    result = run_fork(tmp_path, edit, 2)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("error: per_seed(critic_loss) with 2 seeds: ")
    assert last.endswith(f" (at fork_continuous_action.py:{line + 1})")
    monkeypatch.setenv("RL_UTILS_TRACEBACK", "1")
    assert "Traceback" in run_fork(tmp_path, edit, 2).stderr


@pytest.mark.parametrize("shape", [(3,), (1,), ()])
def test_a_parameter_added_to_a_built_network_is_refused_with_several_seeds(shape):
    """A parameter a fork adds to a network after stack_seeds built it is one tensor for every seed: vmap would cut a
    [num_seeds] one into a part per seed, and stop on another shape with its own error. It runs as written with one
    seed; with several it is refused in one line that names it."""
    for seeds in ([4], [4, 5, 6]):
        net = built(seeds)
        net.scale = nn.Parameter(torch.ones(shape))

        def scaled(x, net):
            return (net(x) * net.scale).pow(2).mean()

        x = torch.randn(len(seeds), 8, 3)
        if len(seeds) == 1:
            assert torch.equal(per_seed(scaled)(x, net), scaled(x[0], net).unsqueeze(0))
            continue
        with pytest.raises(RuntimeError) as refused:
            per_seed(scaled)(x, net)
        assert str(refused.value).startswith(
            f"per_seed(scaled) with 3 seeds: the parameter Projected.scale {list(shape)} is not stacked for the seeds"
        )


def test_a_network_stacked_for_several_seeds_called_outside_per_seed_is_refused():
    x = torch.randn(3, 8, 3)
    assert built([4])(x[0]).shape == (8, 1)  # one seed: a plain network
    net = built([4, 5, 6])
    assert per_seed(net)(x).shape == (3, 8, 1)
    with pytest.raises(RuntimeError, match=r"^Projected, stacked for 3 seeds .* was called outside per_seed: call it through"):
        net(x)


class Shared(nn.Module):
    def __init__(self, encoder, out):
        super().__init__()
        self.encoder, self.head = encoder, nn.Linear(4, out)

    def forward(self, x):
        return self.head(self.encoder(x))


def with_a_shared_encoder():
    """An actor and a critic that share an encoder (a layer with a buffer), as networks() would build them."""
    encoder = nn.Sequential(nn.Linear(3, 4), nn.LayerNorm(4))
    encoder.register_buffer("calls", torch.zeros(()))
    return [Shared(encoder, 2), Shared(encoder, 1)]


def test_a_layer_two_networks_share_stays_shared_and_is_each_seeds_own():
    torch.manual_seed(4)  # as main seeds the process before its first build
    actor, critic = stack_seeds(with_a_shared_encoder, [4, 5, 6], torch.device("cpu"))
    assert actor.encoder is critic.encoder and actor.encoder[0].weight.shape == (3, 4, 3)
    assert actor.encoder.calls.shape == (3,)
    torch.manual_seed(5)
    alone_actor, _ = with_a_shared_encoder()
    assert torch.equal(actor.encoder[0].weight[1], alone_actor.encoder[0].weight)
    assert torch.equal(actor.head.weight[1], alone_actor.head.weight)
    x = torch.randn(3, 8, 3)
    assert per_seed(critic)(x).shape == (3, 8, 1) and per_seed(actor)(x).shape == (3, 8, 2)


def test_an_operation_pytorch_cannot_run_per_seed_is_refused_in_one_line():
    """spectral_norm's power iteration uses an operation vmap has no rule for (torch 2.13: aten::div.out)."""
    (net,) = stack_seeds(lambda: [nn.utils.parametrizations.spectral_norm(nn.Linear(3, 1))], [4, 5], torch.device("cpu"))
    with pytest.raises(RuntimeError) as refused:
        per_seed(net)(torch.randn(2, 8, 3))
    message = str(refused.value)
    assert message.startswith("per_seed(ParametrizedLinear) with 2 seeds: PyTorch cannot run aten::") and "\n" not in message


def test_a_partial_runs_per_seed_with_the_tensor_it_closes_over_shared():
    """functools.partial is how a tensor the seeds share enters a per-seed function (a weight per batch element)."""
    weights = torch.rand(8, 1)

    def weighted(weights, x, net):
        return (net(x) * weights).pow(2).mean()

    x = torch.randn(3, 8, 3)
    net = built([4, 5, 6])
    losses = per_seed(functools.partial(weighted, weights))(x, net)
    for k, seed in enumerate([4, 5, 6]):
        torch.testing.assert_close(losses[k], weighted(weights, x[k], built([seed])))


def test_a_stacked_network_a_per_seed_function_closes_over_is_refused():
    """A network reached inside a per-seed function without being its argument would run on the stacked weights."""
    net, x = built([4, 5, 6]), torch.randn(3, 8, 3)
    with pytest.raises(RuntimeError, match=r"^Projected, stacked for 3 seeds .* was called inside per_seed without being"):
        per_seed(lambda x: net(x).mean())(x)


class Tied(nn.Module):
    """An input and an output layer that share one weight under two names (weight tying)."""

    def __init__(self):
        super().__init__()
        self.encode, self.decode = nn.Linear(3, 3, bias=False), nn.Linear(3, 3, bias=False)
        self.decode.weight = self.encode.weight

    def forward(self, x):
        return self.decode(torch.tanh(self.encode(x)))


def test_a_networks_builder_that_builds_every_seed_alike_is_refused_with_several_seeds():
    """torch.manual_seed(args.seed) inside networks() ("reproducible weights"), or a copy of a network built before:
    every seed would train from the same initial weights. With one seed it is that seed's build."""

    def reseeding():
        torch.manual_seed(1)
        return [Projected()]

    template = Projected()

    def copied():  # a copy of one network built before: every seed the same
        return [copy.deepcopy(template)]

    for builder in (reseeding, copied):
        with pytest.raises(RuntimeError, match=r"^stack_seeds: seeds 4 and 5 were built with the same initial weights"):
            stack_seeds(builder, [4, 5], torch.device("cpu"))
    (one,) = stack_seeds(reseeding, [4], torch.device("cpu"))
    torch.manual_seed(1)
    assert torch.equal(one.head.weight, Projected().head.weight)
    (two,) = stack_seeds(lambda: [Projected()], [4, 5], torch.device("cpu"))  # seeded apart by stack_seeds
    assert not torch.equal(two.head.weight[0], two.head.weight[1])


def test_a_tied_parameter_stays_tied_per_seed():
    torch.manual_seed(4)  # as main seeds the process before its first build
    (net,) = stack_seeds(lambda: [Tied()], [4, 5], torch.device("cpu"))
    assert net.decode.weight is net.encode.weight and net.encode.weight.shape == (2, 3, 3)
    assert len(list(net.parameters())) == 1
    torch.manual_seed(5)
    torch.testing.assert_close(per_seed(net)(torch.ones(2, 1, 3))[1], Tied()(torch.ones(1, 3)))


def test_a_stacked_parameter_replaced_by_load_state_dict_assign_is_refused_naming_assign():
    net = built([4, 5, 6])
    net.load_state_dict({k: v.clone() for k, v in net.state_dict().items()}, assign=True)
    with pytest.raises(RuntimeError, match=r"is not stacked for the seeds \(replaced after stack_seeds built it \("):
        per_seed(loss_fn)(torch.randn(3, 8, 3), net)


def test_a_penalty_over_all_the_stacked_weights_added_outside_per_seed_is_refused_with_several_seeds(tmp_path):
    """An L2 penalty on the critics added to the loss in update, outside per_seed: with one seed it is that seed's;
    with two it is one number over both seeds' weights in each seed's loss (each seed's gradient of it doubled, the
    seeds mixed). Stopped at the first step, naming the loss."""
    anchor = '            optimize(qf_loss, "qf_loss", q_optimizer)\n'
    penalty = "            qf_loss = qf_loss + 1e-3 * sum(p.pow(2).sum() for p in qf.parameters())\n"
    assert_one_seed_runs_and_two_stop(
        tmp_path,
        lambda s: s.replace(anchor, penalty + anchor, 1),
        "error: qf_loss: seed index 0's loss has a gradient in other seeds' weights (a parameter [2, ",
    )


def test_a_reward_wrapper_around_the_evaluation_env_is_refused_and_other_wrappers_pass():
    """Evaluations report the task's return: a reward scaled (or normalised, clipped) by a wrapper around the
    evaluation env would report another number as every evaluation, without a word."""
    import gymnasium as gym

    def still(obs):
        return np.zeros((len(obs), 1), np.float32)

    (plain,) = env_layer.evaluate(still, [env_layer.make_env("Pendulum-v1", 1)], [5], 1)[0]
    scaled = gym.wrappers.TransformReward(env_layer.make_env("Pendulum-v1", 1), lambda r: 0.1 * r)
    with pytest.raises(ValueError, match=r"^evaluate: env 0's episode returned -130\.57.* and -1305\.7.* in the task's"):
        env_layer.evaluate(still, [scaled], [5], 1)
    normalised = gym.wrappers.NormalizeObservation(env_layer.make_env("Pendulum-v1", 1))  # the rewards as they are
    assert env_layer.evaluate(still, [normalised], [5], 1)[0, 0] == plain
    cut = gym.wrappers.TimeLimit(env_layer.make_env("Pendulum-v1", 1), 50)  # shorter episodes: the fork's protocol
    assert env_layer.evaluate(still, [cut], [5], 2).shape == (1, 2)


def test_a_policy_that_draws_from_torchs_generator_in_an_evaluation_is_refused():
    """An actor with dropout evaluated in training mode: each evaluation would draw from torch's generator, which the
    training run draws its noise and batches from, so that the run's numbers would depend on --eval-frequency."""
    actor = nn.Sequential(nn.Linear(3, 8), nn.Dropout(0.1), nn.Linear(8, 1), nn.Tanh())

    def policy(obs):
        with torch.no_grad():
            return actor(torch.as_tensor(obs)).numpy()

    envs = [env_layer.make_env("Pendulum-v1", 1)]
    with pytest.raises(RuntimeError, match=r"^evaluate: the policy drew from torch's random generator \(a dropout"):
        env_layer.evaluate(policy, envs, [5], 1)
    actor.eval()  # the fix the error names: the same policy, deterministic
    before = torch.get_rng_state()
    assert env_layer.evaluate(policy, envs, [5], 1).shape == (1, 1)
    assert torch.equal(torch.get_rng_state(), before)


def test_a_ppo_fork_that_wraps_its_evaluation_env_in_a_reward_scale_stops_and_one_that_wraps_its_training_env_runs(
    tmp_path,
):
    source = open(os.path.join(REPO, "ppo_continuous_action.py")).read()
    made = "make_env(args.env_id, eval_seed, run.video_folders[0], video_every=args.eval_episodes)"
    assert made in source and "    env = make_env(args.env_id, args.seed)\n" in source
    scale = "__import__('gymnasium').wrappers.TransformReward({}, lambda r: 0.1 * r)"
    forks = {
        "eval": source.replace(made, scale.format(made), 1),
        "train": source.replace(
            "env = make_env(args.env_id, args.seed)", "env = " + scale.format("make_env(args.env_id, args.seed)"), 1
        ),
    }
    flags = ["--env-id", "Pendulum-v1", "--total-timesteps", "256", "--num-steps", "128", "--eval-frequency", "256"]
    results = {}
    for name, fork in forks.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "fork_continuous_action.py").write_text(fork)
        command = [sys.executable, "fork_continuous_action.py", *flags, "--eval-episodes", "1"]
        results[name] = forkserver.run(
            command, cwd=tmp_path / name, capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": REPO}
        )
    assert results["train"].returncode == 0, results["train"].stderr
    assert results["eval"].returncode == 1
    assert results["eval"].stderr.strip().splitlines()[-1].startswith("error: evaluate: env 0's episode returned ")


def test_a_ppo_fork_whose_normalizer_gains_a_field_its_state_dict_leaves_out_stops_at_the_first_checkpoint(tmp_path):
    """A reward normaliser of the rewards themselves added to PPO's Normalizer, its state_dict() unchanged: a resumed
    run would start those statistics from zero (a cold hunt measured -1628.2 resumed against -1634.7). Stopped at the
    first checkpoint, naming the field; PPO's own Normalizer comes back whole."""
    source = open(os.path.join(REPO, "ppo_continuous_action.py")).read()
    init = "        self.gamma, self.discounted_return = gamma, 0.0\n"
    use = "        self.return_rms.update(self.discounted_return)\n"
    assert init in source and use in source
    fork = source.replace(init, init + "        self.reward_rms = RunningMeanStd()\n", 1)
    fork = fork.replace(use, use + "        self.reward_rms.update(reward)\n", 1)
    flags = ["--env-id", "Pendulum-v1", "--total-timesteps", "512", "--num-steps", "128", "--eval-frequency", "512"]
    results = {}
    for name, script in (("fork", fork), ("ppo", source)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "fork_continuous_action.py").write_text(script)
        command = [
            sys.executable,
            "fork_continuous_action.py",
            *flags,
            "--eval-episodes",
            "1",
            "--checkpoint-frequency",
            "150",
        ]
        results[name] = forkserver.run(
            command, cwd=tmp_path / name, capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": REPO}
        )
    assert results["ppo"].returncode == 0, results["ppo"].stderr
    assert results["fork"].returncode == 1
    assert (
        results["fork"]
        .stderr.strip()
        .splitlines()[-1]
        .startswith(
            "error: run.start's part `normalizer` (Normalizer) does not come back whole from its state_dict(): "
            "`normalizer.reward_rms.mean` is not what load_state_dict() restores"
        )
    )


def test_the_seeds_losses_reduced_to_one_number_before_optimize_are_refused_with_several_seeds(tmp_path):
    """optimize(qf_loss.mean(), ...): with one seed the same loss; with two, each seed's gradient halved (which SGD
    and clipping by norm keep). Stopped at the first step, naming the loss and the fix."""
    edit = lambda s: s.replace('optimize(qf_loss, "qf_loss"', 'optimize(qf_loss.mean(), "qf_loss"', 1)  # noqa: E731
    assert_one_seed_runs_and_two_stop(
        tmp_path, edit, "error: qf_loss: one number for 2 seeds' weights (a loss of shape []): the seeds' losses were reduced"
    )


TRAINED_SCALE = torch.ones(2, 1, requires_grad=True)  # a fork's per-seed multiplier, named as a global


def scaled_by_the_global(x, net):
    return (net(x) * TRAINED_SCALE).pow(2).mean()


def test_a_trained_tensor_read_from_outside_a_per_seed_functions_arguments_is_refused_with_several_seeds():
    """A [num_seeds, 1] multiplier that is trained (requires grad), closed over, behind a partial or named as a global,
    is read whole by every seed's loss under vmap (and trained by all of them); as an argument each seed gets its
    row. A tensor that is not trained (a constant the seeds share) is the function's to read."""
    net, x = built([4, 5]), torch.randn(2, 8, 3)
    scale = torch.ones(2, 1, requires_grad=True)

    def closed(x, net):
        return (net(x) * scale).pow(2).mean()

    def as_argument(x, net, scale):
        return (net(x) * scale).pow(2).mean()

    partial = functools.partial(lambda scale, x, net: (net(x) * scale).pow(2).mean(), scale)
    held = {"scale": scale}

    def in_a_dict(x, net):
        return (net(x) * held["scale"]).pow(2).mean()

    def by_default(x, net, scale=scale):
        return (net(x) * scale).pow(2).mean()

    found = [(closed, "scale"), (partial, "fn.args[0]"), (scaled_by_the_global, "TRAINED_SCALE"), (in_a_dict, "held['scale']")]
    for fn, label in found + [(by_default, "by_default's default argument 0")]:
        with pytest.raises(RuntimeError, match=rf"with 2 seeds reads `{re.escape(label)}`, a trained tensor \[2, 1\]"):
            per_seed(fn)(x, net)
    assert per_seed(as_argument)(x, net, scale).shape == (2,)
    constant = torch.full((1,), 2.0)  # a constant the seeds share
    assert per_seed(lambda x, net: (net(x) * constant).pow(2).mean())(x, net).shape == (2,)
    weight = torch.ones(1, requires_grad=True)  # one seed: the function as written, a trained tensor read as it reads
    assert per_seed(lambda x, net: (net(x) * weight).pow(2).mean())(x[:1], built([4])).shape == (1,)


def test_the_one_number_check_passes_per_seed_losses_and_losses_without_stacked_weights():
    net = built([4, 5])
    x = torch.randn(2, 8, 3)
    seeds_module.apart_calls.clear()
    seeds_module.check_apart(per_seed(loss_fn)(x, net), "per seed")  # [2]: one per seed
    log_alpha = torch.zeros((), requires_grad=True)
    seeds_module.check_apart(log_alpha * 2.0, "no stacked weights")  # one number of an unstacked tensor
    one = built([4])
    seeds_module.check_apart(per_seed(loss_fn)(x[:1], one).mean(), "one seed")  # one seed: one number is its loss
    for reduce in (torch.mean, torch.sum):
        with pytest.raises(RuntimeError, match=r"^two: one number for 2 seeds' weights \(a loss of shape \[\]\)"):
            seeds_module.check_apart(reduce(per_seed(loss_fn)(x, net)), "two")


def test_the_seeds_apart_check_passes_apart_seeds_and_looks_at_each_losss_first_steps():
    net = built([4, 5, 6])
    x = torch.randn(3, 8, 3)
    seeds_module.apart_calls.clear()
    for _ in range(seeds_module.WATCHED_CALLS):
        seeds_module.check_apart(per_seed(loss_fn)(x, net), "apart")  # nothing crosses the seeds
    mixed = per_seed(loss_fn)(x, net) + net.head.weight.pow(2).sum()
    seeds_module.check_apart(mixed, "apart")  # past its first steps: no longer looked at
    with pytest.raises(RuntimeError, match=r"^mixed: seed index 0's loss has a gradient in other seeds' weights"):
        seeds_module.check_apart(mixed, "mixed")
    # a non-finite gradient (sqrt at 0) is the NaN guard's matter, not a mixing of the seeds
    seeds_module.check_apart(per_seed(lambda x, net: (net(x) - net(x).detach()).pow(2).mean().sqrt())(x, net), "sqrt")


def test_a_hand_written_backward_and_step_stop_with_several_seeds(tmp_path):
    """CleanRL's own lines for the critics' step in place of optimize: the seeds' losses reduced by a mean, each seed's
    gradient divided by the number of seeds, and no check of the loss. With several seeds the optimizer's step stops,
    naming the fix; one seed's run is CleanRL's and runs."""
    by_hand = "            q_optimizer.zero_grad()\n            qf_loss.mean().backward()\n            q_optimizer.step()\n"

    def edit(source):
        assert source.count('            optimize(qf_loss, "qf_loss", q_optimizer)\n') == 1
        return source.replace('            optimize(qf_loss, "qf_loss", q_optimizer)\n', by_hand)

    assert_one_seed_runs_and_two_stop(
        tmp_path,
        edit,
        "error: q_optimizer.step() with 2 seeds: a gradient it applies (a parameter [2, 256, 4]) comes from a loss "
        "optimize did not see",
    )


def test_the_step_watch_passes_optimizes_steps_and_watches_each_optimizers_first_steps():
    net = built([4, 5])
    x = torch.randn(2, 8, 3)
    optimizer = torch.optim.Adam(net.parameters())
    seeds_module.watch_steps({"optimizer": optimizer, "the same one": optimizer}, 2)  # watched once

    def step(backward):
        loss = per_seed(loss_fn)(x, net)
        seeds_module.check_apart(loss, "loss")
        seeds_module.record_checked(loss)  # what optimize's check_finite does
        optimizer.zero_grad()
        backward(loss)
        optimizer.step()

    for _ in range(seeds_module.WATCHED_CALLS - 1):
        step(lambda loss: loss.sum().backward())  # optimize's
    with pytest.raises(RuntimeError, match=r"^optimizer.step\(\) with 2 seeds: a gradient it applies \(a parameter \["):
        optimizer.zero_grad()
        per_seed(loss_fn)(x, net).mean().backward()  # by hand, unchecked: the watch's last step stops it
        optimizer.step()
    step(lambda loss: loss.mean().backward())  # past its first steps: no longer watched
    assert optimizer not in seeds_module.watched_steps
    idle = torch.optim.Adam([torch.zeros(2, requires_grad=True)])  # an optimizer that never steps
    seeds_module.watch_steps({"optimizer": optimizer, "idle": idle}, 2)
    for _ in range(seeds_module.WATCHED_CALLS - 1):
        step(lambda loss: loss.sum().backward())
    for _ in range(seeds_module.WATCH_RECORDS):
        seeds_module.record_checked(per_seed(loss_fn)(x, net))
    assert not seeds_module.watched_steps  # the watch ended with its records, the idle optimizer's with it
    step(lambda loss: loss.mean().backward())
    loss = per_seed(loss_fn)(x, net)
    loss.sum().backward()
    with pytest.raises(RuntimeError, match=r"^late: its graph was freed by a backward before the check of the seeds"):
        seeds_module.check_apart(loss, "late")  # check_finite after the backward
    seeds_module.watch_steps({"optimizer": optimizer}, 1)  # one seed: no watch
    step(lambda loss: loss.mean().backward())
    assert not seeds_module.handles


def test_a_part_whose_state_holds_a_tensor_without_the_seeds_dimension_is_refused_at_the_checkpoint():
    """A fork's part with a 0-d counter or a shared [obs_dim] mean: a checkpoint cuts each tensor into the seeds'
    shares along its first dimension, which these do not have."""
    for tensor in (torch.tensor(0.0), torch.zeros(5)):
        state = {"envs": [{}, {}], "nets": {}, "optimizers": {}, "scale": {"count": tensor}}
        with pytest.raises(ValueError, match=r"^run.start's part `scale`: its state holds `count`, a tensor of shape"):
            split_seeds(state, {"scale": None}, [[], []], ["a", "b"])
    state["scale"] = {"count": torch.zeros(2, 5)}
    assert [c["scale"]["count"].shape for c in split_seeds(state, {"scale": None}, [[], []], ["a", "b"])] == [(1, 5)] * 2


def test_any_object_with_a_state_main_holds_but_does_not_checkpoint_is_refused_at_the_start(tmp_path):
    """A fork's running reward scale (an object with a state_dict) left out of run.start's parts would restart from
    its initial state on --resume: refused before the first step of a run that writes checkpoints."""
    scale = (
        "class RewardScale:\n"
        "    def __init__(self):\n"
        "        self.count = 0\n\n"
        "    def state_dict(self):\n"
        "        return {'count': self.count}\n\n"
        "    def load_state_dict(self, state):\n"
        "        self.count = state['count']\n\n\n"
    )

    def edit(source):
        fork = source.replace("def main(args: Args):\n", scale + "def main(args: Args):\n", 1)
        return fork.replace(SCHEDULER_AT, "    reward_scale = RewardScale()\n" + SCHEDULER_AT, 1)

    result = run_fork(tmp_path, edit, 1, "--checkpoint-frequency", "200")
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: `reward_scale` (RewardScale) has a state_dict() but is not in run.start's parts: a checkpoint would not "
        "hold it, and --resume would start it from its initial state; add it there (run.start(..., "
        "reward_scale=reward_scale))"
    )
    given = run_fork(
        tmp_path,
        lambda s: edit(s).replace("buffer=rb)", "buffer=rb, reward_scale=reward_scale)"),
        1,
        "--checkpoint-frequency",
        "200",
    )
    assert given.returncode == 0, given.stderr


RUNNING_MEAN = (  # CleanRL's running observation statistics, in short: a fork's own class with plain state
    "class RunningMean:\n"
    "    def __init__(self, shape):\n"
    "        self.mean, self.count = np.zeros(shape), 0\n\n"
    "    def update(self, x):\n"
    "        self.count += len(x)\n"
    "        self.mean = self.mean + (x.mean(0) - self.mean) * len(x) / self.count\n\n\n"
)


@pytest.mark.parametrize("updated", [True, False])
def test_an_object_of_the_forks_own_class_whose_plain_state_changes_is_refused_at_a_checkpoint(updated, tmp_path):
    """A fork's RunningMean (arrays and numbers, no state_dict) updated in the loop: no checkpoint holds it, and a
    resumed run would start it from zero. Stopped at the first checkpoint after it changed, naming it; left as made
    (a holder of settings), or in a run that writes no checkpoints, it is the fork's to keep."""

    def edit(source):
        fork = source.replace("def main(args: Args):\n", RUNNING_MEAN + "def main(args: Args):\n", 1)
        fork = fork.replace(SCHEDULER_AT, "    obs_stats = RunningMean(envs.obs_dim)\n" + SCHEDULER_AT, 1)
        add = '        rb.add(obs, infos["real_next_obs"], actions, rewards, terminations)\n'
        return fork.replace(add, add + "        obs_stats.update(obs)\n", 1) if updated else fork

    result = run_fork(tmp_path, edit, 1, "--checkpoint-frequency", "150")
    if not updated:
        assert result.returncode == 0, result.stderr
        return
    assert result.returncode == 1
    assert (
        result.stderr.strip()
        .splitlines()[-1]
        .startswith(
            "error: `obs_stats` (RunningMean), an object of the script's own class, changed since run.start or the checkpoint "
            "that first met it (`obs_stats.mean`), and it is not in run.start's parts: a checkpoint would not hold it"
        )
    )
    assert run_fork(tmp_path, edit, 1).returncode == 0  # no checkpoints: nothing to resume


class ScaleDecay:  # holds a tensor given to run.start: a checkpoint has it
    def __init__(self, scale):
        self.scale = scale


class Stopwatch:  # a number: the update's seconds, for a log
    def __init__(self):
        self.seconds = 0.0


class RunningMeanOf3:
    def __init__(self):
        self.mean = np.zeros(3)


@pytest.mark.parametrize("update", ["an array", "a NumPy number"])
def test_the_own_state_check_leaves_a_part_held_by_an_object_and_numbers_and_stops_a_changed_array(run_of, update):
    run, envs = run_of(checkpoint_frequency=1)
    scale = torch.ones(())
    decay, stopwatch, stats = ScaleDecay(scale), Stopwatch(), RunningMeanOf3()  # noqa: F841 (main holds them)
    stats.count = np.zeros(())  # a scalar RunningMeanStd's: a 0-d array, a NumPy number once updated
    run.start(envs, CPU, {}, {}, scale=scale)
    decay.scale.mul_(0.5)
    stopwatch.seconds += 1.5
    run.end_step(0)  # the checkpoint of step 1: the scale is in it, the seconds are no training state
    if update == "an array":
        stats.mean += 1.0
    else:
        stats.count = stats.count + 1.0  # np.float64
    with pytest.raises(SystemExit) as refused:
        run.end_step(1)
    assert str(refused.value).startswith("error: `stats` (RunningMeanOf3), an object of the script's own class, changed")
    run.logs.close()


class NoiseState:
    """A fork's part: the flags it reads, a scale and a bfloat16 tensor its state_dict holds, a cache load_state_dict
    resets, and `left_out`, which its state_dict forgets."""

    def __init__(self, args):
        self.args, self.scale, self.half, self.cache = args, torch.ones(2), torch.zeros(2, dtype=torch.bfloat16), None
        self.left_out = np.zeros(3)

    def state_dict(self):
        return {"scale": self.scale.clone(), "half": self.half.clone()}

    def load_state_dict(self, state):
        self.scale.copy_(state["scale"]), self.half.copy_(state["half"])
        self.cache = None  # recomputed from the state


def test_a_parts_round_trip_through_its_state_dict_leaves_the_flags_a_cache_and_bf16_and_stops_a_forgotten_field(run_of):
    run, envs = run_of(checkpoint_frequency=1)
    noise = NoiseState(run.args)
    run.start(envs, CPU, {}, {}, noise=noise)
    noise.scale.mul_(0.5), noise.half.add_(1.5)
    noise.cache = noise.scale * 2.0
    run.args.exploration_noise *= 0.5  # a flag decayed in the loop: the checkpoint's flags hold it
    run.end_step(0)  # the checkpoint of step 1: the part comes back whole
    noise.left_out += 1.0
    with pytest.raises(SystemExit) as refused:
        run.end_step(1)
    assert str(refused.value).startswith(
        "error: run.start's part `noise` (NoiseState) does not come back whole from its state_dict(): `noise.left_out` is"
    )
    run.logs.close()


GENERATOR_KINDS = {  # a generator of a fork's own, and three of its draws
    "numpy Generator": (lambda: np.random.default_rng(5), lambda g: g.random(3).tolist()),
    "numpy RandomState": (lambda: np.random.RandomState(5), lambda g: g.random_sample(3).tolist()),
    "random.Random": (lambda: random.Random(5), lambda g: [g.random() for _ in range(3)]),
    "torch.Generator": (lambda: torch.Generator().manual_seed(5), lambda g: torch.rand(3, generator=g).tolist()),
}


@pytest.mark.parametrize("kind", list(GENERATOR_KINDS))
def test_a_generator_given_to_run_start_is_in_each_seeds_checkpoint_and_draws_on_after_a_restore(kind, tmp_path):
    """A part that is a random generator of the script's own: each seed's checkpoint holds its whole state (a process's
    generator, not cut), loadable with weights_only, and a restore sets it back to where the checkpoint was taken."""
    make, draw = GENERATOR_KINDS[kind]
    generator = make()
    draw(generator)
    parts = {"noise_rng": generator}
    state = ckpt.snapshot("fork", types.SimpleNamespace(), [], 0, {}, {}, parts)
    for k, checkpoint in enumerate(split_seeds(state, parts, [[], []], ["a", "b"])):
        torch.save(checkpoint, tmp_path / f"{k}.pt")
    loaded = [torch.load(tmp_path / f"{k}.pt", weights_only=True) for k in range(2)]
    ahead = draw(generator)
    assert draw(generator) != ahead
    ckpt.restore(join_seeds(loaded, parts), [], {}, {}, parts)
    assert draw(generator) == ahead


def with_generator(source, parts=""):
    """TD3 whose exploration noise also draws from a NumPy generator of its own, `noise_rng`, with `parts` added to
    run.start's."""
    fork = source.replace(SCHEDULER_AT, "    noise_rng = np.random.default_rng(args.seed)\n" + SCHEDULER_AT, 1)
    noisy = (
        "            actions = per_seed(noisy_action)(to_device(obs, device), actor, args.exploration_noise).cpu().numpy()\n"
    )
    noised = "            actions = np.clip(actions + noise_rng.normal(0, 0.3, actions.shape), -2, 2).astype(np.float32)\n"
    fork = fork.replace(noisy, noisy + noised).replace("buffer=rb", "buffer=rb" + parts)
    assert fork.count("noise_rng") == 2 + parts.count("noise_rng")
    return fork


def test_a_generator_of_the_forks_own_not_given_to_run_start_is_refused(tmp_path):
    """A fork's own generator left out of run.start's parts would start again on --resume: refused at the start of a
    run that writes checkpoints, as is a part named as a checkpoint's own state (test_a_scheduler_given_to_run_start_...
    resumes one given)."""
    refused = run_fork(tmp_path, with_generator, 1, "--checkpoint-frequency", "300")
    assert refused.returncode == 1
    assert refused.stderr.strip().splitlines()[-1] == (
        "error: `noise_rng` (Generator), a random generator of the script's own, is not in run.start's parts: a checkpoint "
        "would not hold it, and --resume would start it again; add it there (run.start(..., noise_rng=noise_rng)), or "
        "draw from torch's generator, which checkpoints hold"
    )
    taken = run_fork(tmp_path, functools.partial(with_generator, parts=", rng=noise_rng"), 1, "--checkpoint-frequency", "300")
    assert taken.returncode == 1
    assert taken.stderr.strip().splitlines()[-1] == (
        "error: run.start's part `rng`: a checkpoint keeps its own `rng` under that name, which would replace it; give "
        "the part another name (run.start(..., my_rng=...))"
    )


# What main holds and gives run.start, checked in-process: a test function stands in for main (run.start reads its
# caller's names, as it reads main's).
@pytest.fixture
def run_of(tmp_path, monkeypatch):
    """A Run of TD3's flags on Pendulum-v1 (its envs beside it), started from the calling test as from main."""
    from rl_utils.run import Run

    monkeypatch.chdir(tmp_path)
    made = []

    def make(num_seeds=1, **flags):
        args = dataclasses.replace(td3.Args(), env_id="Pendulum-v1", num_seeds=num_seeds, run_name="r{seed}", **flags)
        run = Run(args)
        made.append(SeedEnvs("Pendulum-v1", run.seeds))
        return run, made[-1]

    yield make
    for envs in made:
        envs.close()


CPU = torch.device("cpu")


def test_the_hyperparameters_table_gives_the_flags_as_given_not_as_main_filled_them_in(run_of, tmp_path):
    """A fork's SAC-style flag that main fills in from the task (target_entropy = -action_dim when not given): the
    table plot_results.py names variants by would give every task's runs another value, and every task a column of
    its own."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from plot_results import parse_hyperparameters

    run, envs = run_of()
    given = run.args.exploration_noise
    run.args.exploration_noise = given * 2.0  # main scales it (max_action), after Run() parsed it
    run.start(envs, CPU, {}, {})
    run.logs.close()
    acc = EventAccumulator(str(tmp_path / "runs" / "r1"), size_guidance={"tensors": 0})
    acc.Reload()
    table = parse_hyperparameters(acc.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode())
    assert table["exploration_noise"] == str(given) and table["seed"] == "1"


def test_a_wrapper_around_make_envs_env_given_to_run_start_is_refused_in_a_run_with_checkpoints(run_of):
    """SB3's normalised actions as a Gymnasium wrapper around each env of SeedEnvs: a checkpoint saves and rebuilds an
    env through make_env's EpisodeRecord, beneath the wrapper (its state left out, its observations not seen). One
    line at run.start (it was an AttributeError's traceback at the first checkpoint); without checkpoints, it runs."""
    import gymnasium as gym

    for flags in ({"checkpoint_frequency": 100}, {}):
        run, envs = run_of(**flags)
        envs.envs = [gym.wrappers.RescaleAction(env, np.float32(-1), np.float32(1)) for env in envs.envs]
        if not flags:
            run.start(envs, CPU, {}, {})
            with pytest.raises(SystemExit) as stopped:  # a NaN's last finite state cannot be saved through it
                with run.stop_on_nan(5):
                    raise NonFiniteError("qf_loss")
            assert str(stopped.value).endswith(
                "the last finite state is not saved: the env given to run.start is a RescaleAction, not the env make_env made"
            )
            run.logs.close()
            continue
        with pytest.raises(SystemExit) as refused:
            run.start(envs, CPU, {}, {})
        assert str(refused.value).startswith(
            "error: run.start's env 0 is a RescaleAction, not the env make_env made (or one it wraps): a checkpoint saves"
        )


def test_an_env_stepped_after_its_episode_ended_stops_in_one_line():
    """evaluate(policy, envs, ...) given the training envs ends their episodes; the loop's next envs.step was a
    TypeError's traceback inside the checkpoints' episode record."""
    envs = SeedEnvs("Pendulum-v1", [1])
    envs.reset()
    env_layer.evaluate(lambda obs: np.zeros((len(obs), 1), np.float32), envs, [101], 1)
    with pytest.raises(RuntimeError, match=r"^env.step: the env's episode has ended \(or it was never reset\)"):
        envs.step(np.zeros((1, 1), np.float32))
    envs.reset()
    assert envs.step(np.zeros((1, 1), np.float32))[0].shape == (1, 3)
    envs.close()


def test_a_network_or_optimizer_in_a_list_main_holds_is_refused_unless_given_and_a_layer_of_a_given_network_is_held(
    run_of,
):
    """Optimizers kept in a list (one per critic) are found inside it: left out of run.start's optimizers, --resume
    would start Adam again. A layer of a network given, held by a name of its own, is checkpointed with that network;
    a module without state (a loss) needs no checkpoint."""
    run, envs = run_of()
    qf = nn.ModuleList([nn.Linear(4, 1), nn.Linear(4, 1)])
    q_optimizers = [torch.optim.Adam(q.parameters()) for q in qf]
    with pytest.raises(SystemExit) as refused:
        run.start(envs, CPU, {"qf": qf}, {})
    assert str(refused.value) == (
        "error: `q_optimizers[0]` is not in run.start's optimizers: a checkpoint would not hold it; add it there (each "
        "under a name of its own: 'q_optimizers_0': q_optimizers[0])"
    )
    first_critic, losses = qf[0], {"mse": nn.MSELoss()}  # a layer of a network given; a module without state
    run.start(envs, CPU, {"qf": qf}, {f"q_optimizer_{k}": opt for k, opt in enumerate(q_optimizers)})
    run.logs.close()
    del first_critic, losses


def test_a_compiled_network_is_saved_as_the_network_it_wraps():
    """`actor = torch.compile(actor)` in a fork: --save-model's file loads into the script's own Actor, as
    tools/evaluate.py loads it (the compiled module's state_dict names every tensor `_orig_mod.`...)."""
    net = nn.Linear(3, 2)
    compiled = torch.compile(net)  # compiles at its first call: never here
    assert list(compiled.state_dict()) == ["_orig_mod.weight", "_orig_mod.bias"]
    saved = model_of_seed({"actor": compiled}, 0, 1)["actor"]
    nn.Linear(3, 2).load_state_dict(saved)
    assert torch.equal(saved["weight"], net.weight)


def test_a_compiled_network_is_held_and_checkpointed_as_the_network_it_wraps(run_of):
    """`actor_c = torch.compile(actor)` beside `actor`: the compiled one is the network given, not one left out; and a
    checkpoint of a compiled network resumes into the plain one (and back), under the network's own names."""
    run, envs = run_of(checkpoint_frequency=1)
    actor = nn.Linear(3, 1)
    actor_c = torch.compile(actor)  # compiles at its first call: never here
    run.start(envs, CPU, {"actor": actor_c}, {"actor_optimizer": torch.optim.Adam(actor.parameters())})
    run.end_step(0)  # the checkpoint of step 1
    run.logs.close()
    assert list(torch.load("runs/r1/checkpoint.pt", weights_only=True)["nets"]["actor"]) == ["weight", "bias"]
    weight = actor.weight.detach().clone()
    other, other_envs = run_of()  # the plain network given, the compiled one held beside it
    other.start(other_envs, CPU, {"actor": actor}, {"actor_optimizer": torch.optim.Adam(actor.parameters())})
    other.logs.close()
    del actor, actor_c  # main, resumed, holds only the plain network
    resumed = Run(parse_args(td3.Args, argv=["--resume", "runs/r1"]))
    plain = nn.Linear(3, 1)
    resumed.start(envs, CPU, {"actor": plain}, {"actor_optimizer": torch.optim.Adam(plain.parameters())})
    assert torch.equal(plain.weight, weight)
    resumed.logs.close()


def test_a_tensor_an_optimizer_trains_outside_the_networks_and_parts_is_refused(run_of):
    """A Lagrange multiplier (as SAC's log_alpha) whose optimizer is given but the tensor is not: a checkpoint would
    restore Adam's state and start the multiplier from its initial value. Refused in one line naming it; accepted as a
    tensor part, or inside a part whose state_dict() holds it."""
    run, envs = run_of()
    qf = nn.Linear(4, 1)
    log_beta = torch.zeros(1, requires_grad=True)
    optimizers = {"q_optimizer": torch.optim.Adam(qf.parameters()), "beta_optimizer": torch.optim.Adam([log_beta])}
    with pytest.raises(SystemExit) as refused:
        run.start(envs, CPU, {"qf": qf}, optimizers)
    assert str(refused.value) == (
        "error: `beta_optimizer` trains a tensor (`log_beta`) that is in no network or part given to run.start: a "
        "checkpoint would hold the optimizer's state but not the tensor, and --resume would start it from its initial "
        "value; add it to run.start's parts (run.start(..., log_beta=log_beta))"
    )
    run.start(envs, CPU, {"qf": qf}, optimizers, log_beta=log_beta)
    run.logs.close()
    run, envs = run_of()

    class Multiplier:  # a part with a state_dict() that holds the trained tensor
        def __init__(self):
            self.log_beta = torch.zeros(1, requires_grad=True)

        def state_dict(self):
            return {"log_beta": self.log_beta}

        def load_state_dict(self, state):
            with torch.no_grad():
                self.log_beta.copy_(state["log_beta"])

    multiplier = Multiplier()
    optimizers["beta_optimizer"] = torch.optim.Adam([multiplier.log_beta])
    run.start(envs, CPU, {"qf": qf}, optimizers, multiplier=multiplier)
    run.logs.close()
    run, envs = run_of()  # a state_dict() that copies, nested: the copy is what the checkpoint holds
    multiplier.state_dict = lambda: {"multipliers": {"log_beta": multiplier.log_beta.detach().clone()}}
    run.start(envs, CPU, {"qf": qf}, optimizers, multiplier=multiplier)
    run.logs.close()
    run, envs = run_of()  # a trained buffer of a network given: in its state_dict()
    qf.register_buffer("temperature", torch.ones(1, requires_grad=True))
    optimizers["beta_optimizer"] = torch.optim.Adam([qf.temperature])
    run.start(envs, CPU, {"qf": qf}, optimizers)
    run.logs.close()
    run, envs = run_of()  # SAC's log_alpha given, a second multiplier of its shape and value not
    log_alpha, log_beta = torch.zeros(1, requires_grad=True), torch.zeros(1, requires_grad=True)
    optimizers = {"a_optimizer": torch.optim.Adam([log_alpha]), "beta_optimizer": torch.optim.Adam([log_beta])}
    with pytest.raises(SystemExit, match="`beta_optimizer` trains a tensor \\(`log_beta`\\)"):
        run.start(envs, CPU, {"qf": qf}, optimizers, log_alpha=log_alpha)


def test_an_optimizer_a_network_holds_as_an_attribute_is_refused_unless_given(run_of):
    """Stable-Baselines3's habit, `qf.optimizer = Adam(...)`: the network is given, its optimizer not; --resume would
    start Adam's state again."""
    run, envs = run_of()
    qf = nn.Sequential(nn.Linear(4, 8), nn.Linear(8, 1))
    qf[1].optimizer = torch.optim.Adam(qf.parameters())
    with pytest.raises(SystemExit) as refused:
        run.start(envs, CPU, {"qf": qf}, {})
    assert str(refused.value) == (
        "error: `qf[1].optimizer`, an optimizer a network holds, is not in run.start's optimizers: a checkpoint would not "
        "hold its state, and --resume would start it again; add it there ('qf_1_optimizer': qf[1].optimizer)"
    )
    run.start(envs, CPU, {"qf": qf}, {"q_optimizer": qf[1].optimizer})
    run.logs.close()


@dataclasses.dataclass
class ListFlagArgs(td3.Args):  # a fork's flag that is a list
    noise_scales: typing.List[float] = dataclasses.field(default_factory=lambda: [0.1, 0.2])


def one_critic():
    torch.manual_seed(0)
    qf = nn.Linear(3, 1)
    return {"qf": qf}, {"q_optimizer": torch.optim.Adam(qf.parameters())}


# a flag main scales by 2 before run.start, then changes in the loop by a factor: (decay, its value at the checkpoint)
IN_THE_LOOP = {"decayed": (0.9, 0.18), "back to the value given": (0.5, 0.1)}


@pytest.mark.parametrize("in_the_loop", IN_THE_LOOP)
def test_flags_main_changes_are_made_once_on_resume_and_restored_as_they_were(in_the_loop, run_of):
    """A fork that scales a flag before run.start (Fujimoto's `args.exploration_noise *= max_action`) and changes it in
    the loop: --resume parses the flags as main got them, main scales once more, and run.start puts back the value the
    checkpoint holds, not the scale applied twice (also where the loop brought it back to the value given); the flag
    given again, as benchmark.sh gives it, is no conflict."""
    factor, at_checkpoint = IN_THE_LOOP[in_the_loop]
    run, envs = run_of(checkpoint_frequency=1, exploration_noise=0.1)
    args = run.args
    args.exploration_noise *= 2.0  # main, before run.start: 0.2
    run.start(envs, CPU, *one_critic())
    args.exploration_noise *= factor  # in the loop
    run.end_step(0)  # writes the checkpoint of step 1
    run.logs.close()
    for flags in (["--resume", "runs/r1"], ["--resume", "runs/r1", "--exploration-noise", "0.1"]):
        resumed = parse_args(td3.Args, argv=flags)
        assert resumed.exploration_noise == 0.1  # as main got it
        run = Run(resumed)
        resumed.exploration_noise *= 2.0  # main again
        run.start(envs, CPU, *one_critic())
        assert resumed.exploration_noise == pytest.approx(at_checkpoint)  # not scaled twice
        run.logs.close()


def test_a_list_flag_main_changes_in_place_is_made_once_on_resume(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = ListFlagArgs(env_id="Pendulum-v1", run_name="r{seed}", checkpoint_frequency=1)
    run, envs = Run(args), SeedEnvs("Pendulum-v1", [1])
    args.noise_scales[0] *= 2.0  # main, before run.start, in place
    run.start(envs, CPU, *one_critic())
    run.end_step(0)
    run.logs.close()
    resumed = parse_args(ListFlagArgs, argv=["--resume", "runs/r1", "--noise-scales", "0.1", "0.2"])
    assert resumed.noise_scales == [0.1, 0.2]  # as main got it
    run = Run(resumed)
    resumed.noise_scales[0] *= 2.0
    run.start(envs, CPU, *one_critic())
    assert resumed.noise_scales == [0.2, 0.2]
    run.logs.close()
    envs.close()


def test_state_in_a_list_is_refused_where_checkpoints_are_written(run_of):
    """A generator (or a scheduler, or an object with a state_dict) inside a list main holds is found as one held by
    name is, in a run that writes checkpoints."""
    noise_rngs = [np.random.default_rng(1)]
    run, envs = run_of(checkpoint_frequency=100)
    with pytest.raises(SystemExit, match=re.escape("`noise_rngs[0]` (Generator), a random generator of the script's own")):
        run.start(envs, CPU, {}, {})
    with pytest.raises(SystemExit, match=re.escape("add it there (run.start(..., noise_rngs_0=noise_rngs[0]))")):
        run.start(envs, CPU, {}, {})
    run.start(envs, CPU, {}, {}, noise_rngs_0=noise_rngs[0])
    run.logs.close()


def test_a_generator_inside_a_helper_object_main_holds_is_refused_unless_given(run_of):
    """An OU noise of the fork's own class holds its generator in an attribute: left out of run.start's parts, --resume
    would start it again. Found by a name and in a list, refused where checkpoints are written, until given."""
    noise, noises = OUNoise(), [OUNoise()]
    # no state of their own: the process's generators, which checkpoints hold, and an entropy source
    system, global_torch, helper = random.SystemRandom(), torch.default_generator, OUNoise()
    helper.rng, helper.rngs = np.random.mtrand._rand, [random.SystemRandom()]
    run, envs = run_of(checkpoint_frequency=0)
    run.start(envs, CPU, {}, {})  # no checkpoints: nothing to hold
    run.logs.close()
    run, envs = run_of(checkpoint_frequency=100)
    with pytest.raises(SystemExit) as refused:
        run.start(envs, CPU, {}, {})
    assert str(refused.value) == (
        "error: `noise.rng` (Generator), a random generator of the script's own, is not in run.start's parts: a checkpoint "
        "would not hold it, and --resume would start it again; add it there (run.start(..., noise_rng=noise.rng)), or "
        "draw from torch's generator, which checkpoints hold"
    )
    with pytest.raises(SystemExit, match=re.escape("add it there (run.start(..., noises_0_rng=noises[0].rng))")):
        run.start(envs, CPU, {}, {}, noise_rng=noise.rng)
    noises[0].rngs = {"actor": np.random.default_rng(4)}  # in a dict (or a list) the object holds
    with pytest.raises(
        SystemExit, match=re.escape("add it there (run.start(..., noises_0_rngs_actor=noises[0].rngs['actor']))")
    ):
        run.start(envs, CPU, {}, {}, noise_rng=noise.rng, noises_0_rng=noises[0].rng)
    run.start(envs, CPU, {}, {}, noise_rng=noise.rng, noises_0_rng=noises[0].rng, noises_0_rngs=noises[0].rngs["actor"])
    run.logs.close()
    del system, global_torch


@pytest.mark.parametrize("part", [0.5, {"updates": 0}], ids=["a number", "a dict"])
def test_a_part_resume_cannot_restore_in_place_is_refused(run_of, part):
    """A checkpoint would hold a number's or a dict's value, but --resume cannot put it back into main's own object:
    refused at the start, with the way that works."""
    run, envs = run_of()
    with pytest.raises(SystemExit) as refused:
        run.start(envs, CPU, {}, {}, coef=part)
    assert str(refused.value).startswith(
        f"error: run.start's part `coef` is a {type(part).__name__}, which --resume cannot restore in place"
    )
    assert "coef = torch.tensor(...), then coef.copy_(...) or coef.mul_(...)" in str(refused.value)


def test_a_part_bound_anew_stops_the_run_at_that_step(run_of):
    """A tensor part main binds anew (coef = coef * 0.99) leaves the checkpoint holding the old one: the run stops at
    the step it happens; changed in place, it goes on."""
    run, envs = run_of()
    coef = torch.ones(1)
    run.start(envs, CPU, {}, {}, coef=coef)
    coef.mul_(0.99)
    run.end_step(0)
    coef = coef * 0.99
    with pytest.raises(SystemExit, match=re.escape("`coef` was bound to a new object by step 1: the checkpoints hold")):
        run.end_step(1)
    run.logs.close()


@pytest.mark.parametrize("where, every", [("top of the step", 100), ("after run.end_step", 100), ("top of the step", 250)])
def test_an_evaluation_moved_after_end_step_stops_the_resumed_run_that_would_miss_it(run_of, where, every):
    """The checkpoint run.end_step writes after step 299 comes before an evaluation made after it (at step 300): a run
    resumed from it at step 300 evaluates at 300 only at the top of the step. Made there, as the scripts make it, the
    resumed run's record has every evaluation; made after run.end_step, the resumed run stops at the end of step 300,
    before anything is written, where its record (evaluations every 100 steps) would miss that evaluation. A fork's own
    schedule (every 250 steps, --eval-frequency 100) is its own: resumed at step 100, its record (step 0) puts none
    there."""
    flags = dict(total_timesteps=1000, eval_frequency=100, checkpoint_frequency=100)
    top = where == "top of the step"

    def steps(run, first, last):
        for step in range(first, last):
            if top and step % every == 0:
                run.evaluate(step, np.zeros((1, 1)))
            run.end_step(step)
            if not top and (step + 1) % every == 0:
                run.evaluate(step + 1, np.zeros((1, 1)))

    run, envs = run_of(**flags)
    run.start(envs, CPU, {}, {})
    resume_at = 300 if every == 100 else 100
    steps(run, 0, resume_at + 50)  # killed 50 steps after the checkpoint it resumes from
    run.logs.close()
    resumed, envs = run_of(resume="runs/r1", **flags)
    resumed.start(envs, CPU, {}, {})
    made = {(True, 100): [0, 100, 200], (False, 100): [100, 200], (True, 250): [0]}[(top, every)]
    assert resumed.start_step == resume_at and [s for s, _ in resumed.eval_returns[0]] == made
    if top:
        steps(resumed, resume_at, 501)
        assert [s for s, _ in resumed.eval_returns[0]] == made + ([300, 400, 500] if every == 100 else [250, 500])
    else:
        with pytest.raises(SystemExit) as refused:
            steps(resumed, 300, 301)
        assert str(refused.value).startswith(
            "error: step 300 ended without its evaluation: the run resumed at step 300, where its record's evaluations, "
            "every 100 steps, put the next one"
        )
        assert "evaluate at the top of the step" in str(refused.value)
    resumed.logs.close()


def test_a_fork_that_runs_code_after_end_step_is_refused_at_the_start_of_a_run_with_checkpoints(tmp_path):
    """A critics' reset every 300 steps placed after run.end_step: the checkpoint written there (after step 299) comes
    before the reset, and a run resumed from it never resets at step 300 (a cold hunt measured -1853.9 uninterrupted
    against -1878.4 resumed). Refused at run.start, naming the line; a run without checkpoints has nothing to resume."""
    reset = (
        "        if (global_step + 1) % 300 == 0:  # a primacy-bias reset of the critics\n"
        "            for layer in (m for m in qf.modules() if isinstance(m, nn.Linear)):\n"
        "                layer.reset_parameters()\n"
    )
    edit = lambda s: s.replace(STEP_AT, STEP_AT + reset, 1)  # noqa: E731
    line = edit(td3_source()).splitlines().index(reset.splitlines()[0]) + 1
    error = f"error: main's loop runs code after run.end_step (fork_continuous_action.py:{line}), which writes the checkpoints"
    assert_fork_stops(tmp_path, edit, error, 1, "--checkpoint-frequency", "150")
    assert run_fork(tmp_path, edit, 1).returncode == 0
    before = lambda s: s.replace(STEP_AT, reset + STEP_AT, 1)  # noqa: E731
    assert_runs_with_checkpoints(tmp_path, before)  # before it: in the step


LOOP_AT = "    for global_step in range(run.start_step, args.total_timesteps):\n"


def test_a_number_main_carries_from_step_to_step_stops_a_run_with_checkpoints(tmp_path):
    """An exploration noise decayed in a plain local (noise *= 0.999 a step) is no checkpoint's: a run resumed from
    one would start the decay again, silently. Bound before the loop to what run.start can compute (the flag's value),
    the run stops at its first checkpoint, where the noise has moved; bound to a draw, at run.start. A run without
    checkpoints has nothing to resume; the decay kept in the flag (restored on --resume), or in a tensor given to
    run.start and changed in place, is fine."""
    acting = "actor, args.exploration_noise)"

    def edit(source, noise="noise", given=False, initial="args.exploration_noise"):
        source = source.replace(LOOP_AT, f"    noise = {initial}\n" + LOOP_AT, 1).replace(acting, f"actor, {noise})", 1)
        if given:
            source = source.replace(
                "    obs = run.start(", "    noise = torch.full((args.num_seeds, 1), 0.1)\n    obs = run.start(", 1
            )
            source = source.replace("buffer=rb)", "buffer=rb, noise=noise)", 1).replace(f"    noise = {initial}\n", "", 1)
        return source.replace(
            STEP_AT, f"        {noise} *= 0.999  # an exploration noise annealed step by step\n" + STEP_AT, 1
        )

    fork = edit(td3_source())
    assert "noise *= 0.999" in fork and "actor, noise)" in fork
    line = next(i for i, text in enumerate(fork.splitlines(), 1) if "actor, noise)" in text)
    carries = f"error: main's loop carries `noise` from one step to the next (fork_continuous_action.py:{line}), and "
    moved = (
        "by step 150 it is no longer what it was before the loop: no checkpoint holds it, so --resume would start it "
        "again from that value; keep it where a checkpoint holds it"
    )
    assert_fork_stops(tmp_path, edit, carries + moved, 1, "--checkpoint-frequency", "150")
    drawn = functools.partial(edit, initial="np.random.uniform(0.05, 0.15)")
    set_at = fork.splitlines().index("    noise = args.exploration_noise") + 1
    unknown = (
        "no checkpoint holds it: --resume would start it again from its value before the loop (fork_continuous_action.py:"
        f"{set_at}); keep it where a checkpoint holds it"
    )
    assert_fork_stops(tmp_path, drawn, carries + unknown, 1, "--checkpoint-frequency", "150")
    assert run_fork(tmp_path, edit, 1).returncode == 0
    in_flag = functools.partial(edit, noise="args.exploration_noise")
    assert_runs_with_checkpoints(tmp_path, in_flag)
    in_part = functools.partial(edit, given=True)
    assert "noise=noise)" in in_part(td3_source())
    assert run_fork(tmp_path, in_part, 2, "--checkpoint-frequency", "150").returncode == 0


UPDATE_AT = "    def update(batch: Batch, policy_step: bool) -> dict:\n"
UPDATE_BODY_AT = "        with bf16_autocast(device, args.bf16):\n"


def test_a_counter_a_function_of_main_rebinds_stops_a_run_with_checkpoints(tmp_path):
    """A count of updates kept in main's `num_updates` and rebound by `update` (nonlocal), driving a schedule: a run
    resumed from a checkpoint would start it again from 0 (a cold hunt: -1563.4 uninterrupted, -1562.5 resumed). Stops
    at the first checkpoint where it has moved; a run without checkpoints runs."""

    def edit(source):
        source = source.replace(UPDATE_AT, "    num_updates = 0  # gradient steps taken\n\n" + UPDATE_AT, 1)
        counted = "        nonlocal num_updates\n        num_updates += 1\n"
        return source.replace(UPDATE_BODY_AT, counted + UPDATE_BODY_AT, 1)

    fork = edit(td3_source())
    stop = (
        f"error: `update` rebinds main's `num_updates` (nonlocal, fork_continuous_action.py:{line_of(fork, 'nonlocal num_')}),"
        " which main's loop carries from one step to the next, and by step 300 it is no longer what it was before the loop"
    )
    assert_stops_only_with_checkpoints(tmp_path, edit, stop)


def test_a_reset_from_fresh_copies_and_a_value_a_function_stashes_run_with_checkpoints(tmp_path):
    """What the checks above leave alone: a reset at step 250 that loads a fresh critic (through a function main
    defines) and a fresh optimizer into the ones given, both still held by main at later checkpoints; and a value
    `update` overwrites each time (nonlocal last_qf_loss; last_qf_loss = ...), not carried from step to step."""
    reset = (
        "        if global_step == 250:  # reset the critics and their optimizer's state\n"
        "            fresh_qf = stack_seeds(networks, run.seeds, device)[1]\n"
        "            reset_critics()\n"
        "            fresh_optimizer = adam(qf.parameters(), lr=args.learning_rate)\n"
        "            q_optimizer.load_state_dict(fresh_optimizer.state_dict())\n"
    )
    helper = "    def reset_critics():\n        qf.load_state_dict(fresh_qf.state_dict())\n\n"
    stash = "        nonlocal last_qf_loss\n        last_qf_loss = None\n"

    def edit(source):
        source = source.replace(UPDATE_AT, "    last_qf_loss = None\n\n" + helper + UPDATE_AT, 1)
        source = source.replace(UPDATE_BODY_AT, stash + UPDATE_BODY_AT, 1)
        return source.replace(STEP_AT, reset + STEP_AT, 1)

    assert "reset_critics()" in edit(td3_source()) and "nonlocal last_qf_loss" in edit(td3_source())
    assert_runs_with_checkpoints(tmp_path, edit)


def test_a_module_level_counter_a_function_rebinds_stops_a_run_with_checkpoints(tmp_path):
    """The same count kept at the script's module level and rebound by a function of the script (global): no checkpoint
    holds it either."""

    def edit(source):
        counter = "UPDATES = 0\n\n\ndef counted():\n    global UPDATES\n    UPDATES += 1\n\n\n"
        source = source.replace("def main(args: Args):\n", counter + "def main(args: Args):\n", 1)
        return source.replace(UPDATE_BODY_AT, "        counted()\n" + UPDATE_BODY_AT, 1)

    fork = edit(td3_source())
    stop = (
        f"error: `counted` rebinds the script's module-level `UPDATES` (global, fork_continuous_action.py:"
        f"{line_of(fork, 'global UPDATES')}), and by step 300 it is no longer what it was at run.start: no checkpoint holds it"
    )
    assert_stops_only_with_checkpoints(tmp_path, edit, stop)


def test_a_counter_a_function_changes_in_place_stops_a_run_with_checkpoints(tmp_path):
    """The same count kept where a function changes it without rebinding a name: in a list of main's (`counts[0] +=
    1` in `update`), as an attribute of `update` itself (`update.calls += 1`), or in a dict at the script's module
    level (`STATS["updates"] += 1`). No checkpoint holds any of them: each stops at the first checkpoint where it has
    moved, and runs without checkpoints."""

    def in_list(source):
        source = source.replace(UPDATE_AT, "    counts = [0]  # gradient steps taken\n\n" + UPDATE_AT, 1)
        return source.replace(UPDATE_BODY_AT, "        counts[0] += 1\n" + UPDATE_BODY_AT, 1)

    fork = in_list(td3_source())
    stop = (
        f"error: `update` changes main's `counts` in place (`counts[0] += 1`, fork_continuous_action.py:"
        f"{line_of(fork, 'counts[0] += 1')}), which main's loop carries from one step to the next, and by step 300 it is no "
        "longer what it was before the loop"
    )
    assert_stops_only_with_checkpoints(tmp_path, in_list, stop)

    def as_attribute(source):
        source = source.replace("    obs = run.start(", "    update.calls = 0\n    obs = run.start(", 1)
        return source.replace(UPDATE_BODY_AT, "        update.calls += 1\n" + UPDATE_BODY_AT, 1)

    fork = as_attribute(td3_source())
    stop = (
        f"error: `update` changes an attribute of main's `update` (`update.calls += 1`, fork_continuous_action.py:"
        f"{line_of(fork, 'update.calls += 1')}), which main's loop carries from one step to the next, and by step 300"
    )
    assert_stops_only_with_checkpoints(tmp_path, as_attribute, stop)

    def in_module_dict(source):
        counter = 'STATS = {"updates": 0}\n\n\ndef counted():\n    STATS["updates"] += 1\n\n\n'
        source = source.replace("def main(args: Args):\n", counter + "def main(args: Args):\n", 1)
        return source.replace(UPDATE_BODY_AT, "        counted()\n" + UPDATE_BODY_AT, 1)

    line = line_of(in_module_dict(td3_source()), '    STATS["updates"] += 1')
    stop = (
        f"error: `counted` changes the script's module-level `STATS` in place (`STATS['updates'] += 1`, "
        f"fork_continuous_action.py:{line}), and by "
        "step 300 it is no longer what it was at run.start"
    )
    assert_stops_only_with_checkpoints(tmp_path, in_module_dict, stop)


def test_a_draw_between_run_start_and_the_loop_stops_a_run_with_checkpoints(tmp_path):
    """A fixed random prior (or a fresh network) drawn after run.start: a run resumed from a checkpoint draws it from
    the checkpoint's generator, not as the run began (a cold hunt: -1758.0 uninterrupted, -1742.9 resumed). Stops as
    the loop begins; drawn before run.start (drawn again as the run began on --resume), or without checkpoints, it runs."""
    prior = "    prior = torch.randn(obs_dim, device=device)  # a fixed random prior direction\n"
    used = "        actions = per_seed(noisy_action)(to_device(obs, device) + 0 * prior"

    def edit(source, at=LOOP_AT):
        source = source.replace(at, prior + at, 1)
        return source.replace("        actions = per_seed(noisy_action)(to_device(obs, device)", used, 1)

    assert used in edit(td3_source())
    drawn = (
        "error: main drew from torch's random generator between run.start and its loop (a random prior, a fresh network "
        "built there): a run resumed from a checkpoint would draw it from the checkpoint's generator"
    )
    assert_stops_only_with_checkpoints(tmp_path, edit, drawn)
    before = functools.partial(edit, at="    obs = run.start(")
    assert_runs_with_checkpoints(tmp_path, before)
    warm_up = "    if not run.checkpoints:  # a fresh run only: a resumed one skips it\n        torch.randn(3)\n"
    fresh_only = lambda s: s.replace(LOOP_AT, warm_up + LOOP_AT, 1)  # noqa: E731
    assert_runs_with_checkpoints(tmp_path, fresh_only)


def test_logging_past_the_loop_step_stops_a_run_with_checkpoints(tmp_path):
    """Losses logged on another axis than the loop's step (REDQ's updates: step x utd_ratio): a run resumed from a
    checkpoint starts its logs again at the checkpoint's step, erasing every point logged at or after it, which it
    does not log again (a cold hunt: the point at 2020 lost). Stops at the checkpoint; without checkpoints it runs."""
    edit = lambda s: s.replace("run.log(logs, global_step)", "run.log(logs, global_step * 10)", 1)  # noqa: E731
    assert "global_step * 10)" in edit(td3_source())
    stop = "error: run.log logged at step 2000 by the checkpoint at step 300: a run resumed from it would erase what is"
    assert_stops_only_with_checkpoints(tmp_path, edit, stop)


def test_an_attribute_main_gives_args_after_run_start_and_changes_stops_a_run_with_checkpoints(tmp_path):
    """A count kept on args, set after run.start and counted up in the loop: --resume restores args at run.start and
    main sets it again (a cold hunt: 50 uninterrupted, 0 resumed). Stops at the first checkpoint; set before run.start
    (which --resume restores) it runs."""

    def edit(source, at=LOOP_AT):
        source = source.replace(at, "    args.acted = 0  # steps the actor chose\n" + at, 1)
        return source.replace(STEP_AT, "        args.acted += 1\n" + STEP_AT, 1)

    stop = (
        "error: main sets `args.acted` after run.start, and by step 150 it is no longer what it was after the loop's "
        "first step: --resume restores args at run.start"
    )
    assert_stops_only_with_checkpoints(tmp_path, edit, stop)
    before = functools.partial(edit, at="    obs = run.start(")
    assert_runs_with_checkpoints(tmp_path, before)
    recomputed = "        args.frac = 1 - global_step / args.total_timesteps  # set anew at each step\n"
    anew = lambda s: s.replace(STEP_AT, recomputed + STEP_AT, 1)  # noqa: E731
    assert_runs_with_checkpoints(tmp_path, anew)


def test_another_name_of_a_held_weight_changed_in_place_runs_with_checkpoints(tmp_path):
    """A weight decayed by hand through another name (w = actor.fc_mu.weight; w.mul_(0.9999)): the checkpoints hold
    it, under the network's name, so a run with checkpoints runs; bound before run.start or after it."""

    def edit(source, at=LOOP_AT):
        source = source.replace(at, "    decayed = actor.fc_mu.weight\n" + at, 1)
        return source.replace(STEP_AT, "        with torch.no_grad():\n            decayed.mul_(0.9999)\n" + STEP_AT, 1)

    for at in (LOOP_AT, "    obs = run.start("):
        assert_runs_with_checkpoints(tmp_path, functools.partial(edit, at=at))


def test_changed_by_finds_what_a_function_carries_from_call_to_call():
    """What a function changes that outlives its call: a name it rebinds from its own value (nonlocal, global), one it
    changes in place (from its own value, however written: += on an entry, a new item, x[k] = x[k] + 1, an in-place
    method, x.copy_(f(x))), an attribute of a function it changes from its value, its own mutable default argument.
    Not its own names (parameters, locals, a function it defines), a stash it overwrites (nonlocal last; last = x), an
    entry it sets (cache[k] = v), a tensor it overwrites or draws into whole before changing it (fill_, bernoulli_),
    a list it empties first, an attribute of another object, nor what a function it defines changes."""
    from rl_utils.run import changed_by

    source = textwrap.dedent(
        """
        def update(x, counts_given, n=[0], *, seen={}):
            nonlocal total, last, listed
            global UPDATES
            total += x
            last = x
            UPDATES = UPDATES + 1
            listed.append(x)
            counts[0] += 1
            history.append(x)
            stats["a"]["n"] += 1
            tally["n"] = tally.get("n", 0) + 1
            update.calls += 1
            update.seen = getattr(update, "seen", 0) + 1
            other.calls += 1
            self_like.stats["n"] += 1
            counts_given.append(x)
            own = []
            own.append(x)
            cache["x"] = x
            noise.mul_(0.99)
            ema.copy_(0.9 * ema + x)
            target.copy_(x)
            scratch.fill_(0.0)
            scratch.add_(1.0)
            mask.bernoulli_(0.5)
            logs.clear()
            logs.append(x)
            n[0] += 1
            tally2["n"] = 0  # set anew at each call, then counted: nothing carried
            tally2["n"] += 1
            buf[i] = torch.as_tensor(x, dtype=buf.dtype)
            adv[t] = r[t] + g * adv[t + 1]

            def inner(y, acc=[]):
                inner_list.append(1)
                acc.append(y)
        """
    )
    function = ast.parse(source).body[0]
    found = [(name, how, text) for name, _, how, text in changed_by(function, {"update"})]
    assert found == [
        ("total", "nonlocal", "nonlocal total, last, listed"),
        ("UPDATES", "global", "global UPDATES"),
        ("listed", "in place", "listed.append(x)"),
        ("counts", "in place", "counts[0] += 1"),
        ("history", "in place", "history.append(x)"),
        ("stats", "in place", "stats['a']['n'] += 1"),
        ("tally", "in place", "tally['n'] = tally.get('n', 0) + 1"),
        ("update", "attribute", "update.calls += 1"),
        ("noise", "in place", "noise.mul_(0.99)"),
        ("ema", "in place", "ema.copy_(0.9 * ema + x)"),
    ]
    defaults = [(name, how, text) for name, _, how, text in changed_by(ast.parse(source).body[0], set())]
    assert ("update", "default", "n[0] += 1") in defaults and ("update", "attribute", "update.calls += 1") not in defaults
    inner = ast.parse(source).body[0].body[-1]
    assert [(name, how) for name, _, how, _ in changed_by(inner)] == [("inner_list", "in place"), ("inner", "default")]


def test_a_default_argument_of_a_function_inside_mains_function_is_not_mains():
    """A function's own function changing its default argument is not one of main's names to compare (it was a
    KeyError at run.start); main's own function doing so is."""
    from rl_utils.run import carried_locals

    def nested(run):
        def update(x):
            def inner(y, acc=[]):
                acc.append(y)

            inner(x)

        def counted(x, n=[0]):
            n[0] += 1

        for step in range(3):
            update(step)
            counted(step)
            run.end_step(step)

    assert [(c.name, c.how, c.via) for c in carried_locals(nested.__code__)] == [("counted", "default", "counted")]


BONUS = """
def reward_bonus_learner(obs_dim, action_dim, scale=0.1):
    model = nn.Sequential(nn.Linear(obs_dim + action_dim, 64), nn.ReLU(), nn.Linear(64, 1))
    optimizer = optim.Adam(model.parameters(), lr=1e-3)

    def learn(batch):
        predicted = model(torch.cat([batch.observations[0], batch.actions[0]], -1)).squeeze(-1)
        loss = ((predicted - batch.rewards[0]) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return batch._replace(rewards=batch.rewards + scale * (predicted.detach() - batch.rewards[0]).abs().unsqueeze(0))

    return learn


"""
SAMPLED = "update(rb.sample(args.batch_size), policy_step)"


def test_a_network_a_function_main_holds_closes_over_is_refused_at_the_start(tmp_path):
    """A reward model and its optimizer built in a helper whose returned function main holds (a closure): a checkpoint
    would not hold them, and --resume would start them again (a cold hunt: -1521.5 uninterrupted, -1536.7 resumed).
    Refused before the first step, with or without checkpoints; the same helper held through functools.partial too."""

    def edit(source, held="reward_bonus_learner(obs_dim, action_dim)", at="    obs = run.start("):
        source = source.replace("def main(args: Args):\n", BONUS + "def main(args: Args):\n", 1)
        source = source.replace(at, f"    with_bonus = {held}\n" + at, 1)
        return source.replace(SAMPLED, SAMPLED.replace("rb.sample(args.batch_size)", "with_bonus(rb.sample(args.batch_size))"))

    assert "with_bonus(rb.sample(" in edit(td3_source())
    closure = "error: with_bonus's `model` is a network that run.start's nets do not hold: a checkpoint would not hold it"
    assert_fork_stops(tmp_path, edit, closure, 1)
    partial = "functools.partial(lambda learn, batch: learn(batch), reward_bonus_learner(obs_dim, action_dim))"
    through = "error: with_bonus's argument 0's `model` is a network that run.start's nets do not hold"
    assert_fork_stops(tmp_path, functools.partial(edit, held=partial), through, 1)
    after_start = functools.partial(edit, at=LOOP_AT)  # built after run.start: its draw is met as the loop begins
    drawn = "error: main drew from torch's random generator between run.start and its loop"
    assert_stops_only_with_checkpoints(tmp_path, after_start, drawn)  # without a checkpoint, nothing to resume


BONUS_OBJECT = """
class RewardBonus:
    def __init__(self, obs_dim, action_dim):
        self.model = nn.Sequential(nn.Linear(obs_dim + action_dim, 64), nn.ReLU(), nn.Linear(64, 1))
        self.optimizer = optim.Adam(self.model.parameters(), lr=1e-3)

    def learn(self, batch):
        return reward_bonus_learner(0, 0, model=self.model, optimizer=self.optimizer)(batch)


"""
HELD = {  # how main holds the helper: what the stop names
    "a helper object": ("RewardBonus(obs_dim, action_dim)", "with_bonus.model is a network"),
    "its bound method": ("RewardBonus(obs_dim, action_dim).learn", "with_bonus's object.model is a network"),
    "in a list": ("[reward_bonus_learner(obs_dim, action_dim)][0:1]", "with_bonus[0]'s `model` is a network"),
    "a default argument": (
        "(lambda batch, model=nn.Linear(3, 1): batch)",
        "with_bonus's default 0 is a network",
    ),
}


@pytest.mark.parametrize("how", HELD)
def test_a_network_main_reaches_through_an_object_or_a_function_is_refused_at_the_start(how, tmp_path):
    """The reward model held another way than by a closure main names: as an attribute of an object of the script's
    own class, through a bound method's object, a closure in a list, a function's default argument."""
    helper = BONUS.replace("scale=0.1):", "scale=0.1, model=None, optimizer=None):")
    helper = helper.replace("    model = nn.Sequential(", "    model = model or nn.Sequential(")
    helper = helper.replace("    optimizer = optim.Adam(", "    optimizer = optimizer or optim.Adam(")
    held, stop = HELD[how]

    def edit(source):
        source = source.replace("def main(args: Args):\n", helper + BONUS_OBJECT + "def main(args: Args):\n", 1)
        return source.replace("    obs = run.start(", f"    with_bonus = {held}\n    obs = run.start(", 1)

    assert_fork_stops(tmp_path, edit, f"error: {stop} that run.start's nets do not hold", 1)


def test_one_alpha_for_every_seed_is_refused_at_the_start(tmp_path):
    """A SAC fork back to CleanRL's one log_alpha, [1], with two seeds: one temperature every seed trains and reads (a
    cold hunt: seed 1's return moved from -1828.7 to -1825.5 when only seed 2's env changed). Refused at run.start,
    with or without checkpoints; with one seed it runs."""
    sac_source = source("sac")
    per_seed_alpha = "    log_alpha = torch.zeros(len(run.seeds), 1, requires_grad=True, device=device)"
    assert per_seed_alpha in sac_source
    fork = sac_source.replace(per_seed_alpha, "    log_alpha = torch.zeros(1, requires_grad=True, device=device)", 1)
    stop = "error: run.start's part `log_alpha`: its state holds `log_alpha`, a tensor of shape [1], but with 2 seeds"
    assert_fork_stops(tmp_path, lambda _: fork, stop, 2)


def test_a_tensor_a_network_holds_as_a_plain_attribute_stops_a_run_with_checkpoints_once_it_changes(tmp_path):
    """A PPO fork's value scale kept as a plain tensor attribute of Agent (not a buffer), moved after each rollout: a
    network's state_dict() leaves it out, so --resume would start it again (a cold hunt: -1434.7 resumed, -1411.6
    uninterrupted). Stops at the first checkpoint after it moved, as a non-persistent buffer too; as a buffer it runs, and
    so does a layer under torch's weight_norm, whose weight is a plain attribute computed anew at each forward."""
    ppo = source("ppo")
    logstd = "        self.actor_logstd = nn.Parameter(torch.zeros(action_dim))\n"
    value = "        return self.critic(x).squeeze(-1)\n"
    update = "            with run.stop_on_nan(global_step):\n                stats = update_policy("
    assert logstd in ppo and value in ppo and update in ppo
    flags = ["--env-id", "Pendulum-v1", "--num-steps", "128", "--total-timesteps", "512", "--eval-frequency", "512"]
    flags += ["--eval-episodes", "1", "--checkpoint-frequency", "200", "--run-name", "r{seed}"]

    def run(fork: str):
        (tmp_path / "fork_continuous_action.py").write_text(fork)
        command = [sys.executable, str(tmp_path / "fork_continuous_action.py"), *flags]
        env = {**os.environ, "PYTHONPATH": REPO}
        return forkserver.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)

    def fork(held):
        edited = ppo.replace(logstd, logstd + f"        {held}\n", 1).replace(
            value, "        return self.critic(x).squeeze(-1) * self.value_scale\n", 1
        )
        return edited.replace(update, "            agent.value_scale.lerp_(returns.std(), 0.1)\n" + update, 1)

    result = run(fork("self.value_scale = torch.ones(())"))
    assert result.returncode == 1, result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith("error: `agent.value_scale`, a tensor a network holds as a plain attribute or a non-persistent ")
    assert "changed since run.start" in line and "self.register_buffer('value_scale', ...), persistent" in line
    result = run(fork("self.register_buffer('value_scale', torch.ones(()), persistent=False)"))
    assert result.returncode == 1 and "error: `agent.value_scale`, a tensor a network holds" in result.stderr
    result = run(fork("self.register_buffer('value_scale', torch.ones(()))"))
    assert result.returncode == 0, result.stderr
    # torch's weight_norm keeps the weight it computes before each forward as a plain attribute: a cache, not state
    critic_head = "layer_init(nn.Linear(64, 1), std=1.0)"
    assert critic_head in ppo
    result = run(ppo.replace(critic_head, f"torch.nn.utils.weight_norm({critic_head})", 1))
    assert result.returncode == 0, result.stderr


NOISE_MAKER = """
def noise_maker(seed):
    rng = np.random.default_rng(seed)

    def noise(shape):
        return rng.normal(0.0, 0.1, size=shape).astype(np.float32)

    return noise


"""


def test_a_generator_a_function_main_holds_closes_over_is_refused_in_a_run_with_checkpoints(tmp_path):
    """Extra exploration noise from a NumPy generator a helper's returned function closes over: a checkpoint would not
    hold the generator, and --resume would draw again from its start. Refused at run.start where checkpoints are
    written; a run without them runs."""
    acted = (
        "            actions = per_seed(noisy_action)(to_device(obs, device), actor, args.exploration_noise).cpu().numpy()\n"
    )

    def edit(source):
        source = source.replace("def main(args: Args):\n", NOISE_MAKER + "def main(args: Args):\n", 1)
        source = source.replace("    obs = run.start(", "    extra_noise = noise_maker(args.seed)\n    obs = run.start(", 1)
        added = "            actions = (actions + extra_noise(actions.shape)).clip(-2.0, 2.0)\n"
        return source.replace(acted, acted + added, 1)

    assert "extra_noise(actions.shape)" in edit(td3_source())
    stop = "error: extra_noise's `rng` (Generator) has a state that run.start's parts do not hold: a checkpoint would not hold"
    assert_stops_only_with_checkpoints(tmp_path, edit, stop)


def test_a_network_of_the_scripts_module_is_refused_at_the_start(tmp_path):
    """A network built at the script's module level draws its weights as the script is imported, before main seeds
    torch's generator (another draw in every process: a cold hunt's three runs of one seed ended -1522.8, -1510.3 and
    -1505.3), and no checkpoint holds it: refused before the first step, even given to run.start."""

    def edit(source, given=False):
        model = "reward_model = nn.Sequential(nn.Linear(3, 64), nn.ReLU(), nn.Linear(64, 1))\n\n\n"
        source = source.replace("def main(args: Args):\n", model + "def main(args: Args):\n", 1)
        return source.replace("    nets = {", "    nets = {'reward_model': reward_model, ", 1) if given else source

    stop = "error: `reward_model`, a network of the script's module (built as the script is imported), starts from weights"
    assert_fork_stops(tmp_path, edit, stop, 1)
    assert_fork_stops(tmp_path, functools.partial(edit, given=True), stop, 1)


def test_a_sum_carried_through_an_episode_stops_at_a_checkpoint_within_the_episode(tmp_path):
    """An episode's return summed in a plain local, set to 0.0 as the episode ends: at a checkpoint between episodes
    (Pendulum's end every 200 steps) it is what it was before the loop, and --resume starts it there; at one within an
    episode it is not, and the run stops at that checkpoint."""
    summed = (
        "        episode_return += float(rewards[0])\n"
        "        if terminations[0] or truncations[0]:\n"
        "            episode_return = 0.0\n"
    )

    def edit(source):
        source = source.replace(LOOP_AT, "    episode_return = 0.0\n" + LOOP_AT, 1)
        return source.replace(STEP_AT, summed + STEP_AT, 1)

    assert run_fork(tmp_path, edit, 1, "--checkpoint-frequency", "200").returncode == 0
    line = edit(td3_source()).splitlines().index(summed.splitlines()[0]) + 1
    error = (
        f"error: main's loop carries `episode_return` from one step to the next (fork_continuous_action.py:{line}), and by "
        "step 150 it is no longer what it was before the loop: no checkpoint holds it"
    )
    assert_fork_stops(tmp_path, edit, error, 1, "--checkpoint-frequency", "150")


def test_carried_locals_finds_what_a_loop_reads_before_it_sets_it_or_changes_in_place():
    from torch.nn import init

    from rl_utils.run import carried_locals

    def decayed(run, args, log_alpha):
        noise = args.noise
        obs = run.start(log_alpha=log_alpha)  # restored: what the run gives, and names computed from it
        obs = obs if obs is not None else 0
        alpha = log_alpha.exp()  # after run.start, from what it was given
        for step in range(run.start_step, 9):
            action = obs + noise * alpha
            noise *= 0.99
            log_alpha *= 0.5  # a part, changed in place
            obs, alpha = action, log_alpha.exp()
            run.end_step(step)

    def kept(run):
        best, hidden, updates = -1e9, None, 0
        returns, counts = [], {"n": 0}
        seeds = len(run.seeds)  # computed from the run, not restored by it
        for step in range(3):
            ret, hidden = step, (hidden, step)  # a recurrent state
            best = max(best, ret)
            if step % 2:
                updates += seeds
            squares = [x * x for x in range(step)]  # a comprehension's own name
            returns.append(ret)
            counts["n"] += 1
            run.end_step(len(squares))

    def overwritten(run):  # written whole before it is read, at each step
        actions, alpha, logs = np.zeros(2), torch.zeros(1), {}
        recent = collections.deque(maxlen=3)
        for step in range(3):
            actions[:] = step
            alpha.copy_(torch.tensor(float(step)))
            logs.update(loss=step)
            init.zeros_(alpha)  # a module's function, not a local changed in place
            run.end_step(int(actions[0] + alpha + logs["loss"] + len(recent)))

    def counted(run):
        step = run.start_step
        if (first := run.start()) is None:
            first = 0
        while step < 3:
            last = step + first
            run.end_step(step)
            step += 1
        return last

    def set_first(run):
        x = 0
        for step in range(3):
            x = step * 2
            x += 1
            run.end_step(x)

    def counted_from_zero(run):
        step = 0
        while step < 3:
            run.end_step(step)
            step += 1

    def smoothed(run):
        ema = torch.zeros(1)
        for step in range(3):
            ema.copy_(0.9 * ema + step)  # from its own value
            run.end_step(step)

    def emptied(run):  # emptied before it is added to, at each step
        logs = []
        for step in range(3):
            logs.clear()
            logs.append(step)
            run.end_step(len(logs))

    def without_end_step(run):
        total = 0
        for step in range(3):
            total += step

    def found(fn, given=()):
        first = fn.__code__.co_firstlineno
        carried = carried_locals(fn.__code__, set(given))
        return [(c.name, c.line - first, c.set_at - first, c.value and ast.unparse(c.value)) for c in carried]

    assert found(decayed, {"log_alpha"}) == [("noise", 6, 1, "args.noise")]
    assert found(kept) == [
        ("hidden", 5, 1, "None"),
        ("best", 6, 1, "-1000000000.0"),
        ("updates", 8, 1, "0"),
        ("returns", 10, 2, "[]"),
        ("counts", 11, 2, "{'n': 0}"),
    ]
    assert found(counted_from_zero) == [("step", 2, 1, "0")]
    assert found(smoothed) == [("ema", 3, 1, "torch.zeros(1)")]
    for fine in (overwritten, counted, set_first, emptied, without_end_step):
        assert found(fine) == [], fine.__name__


def test_a_value_main_binds_after_run_start_is_computed_there_where_it_makes_only_numbers_and_containers():
    """What a carried local is before the loop, bound after run.start: computed at run.start from main's names where
    the expression calls only makers of numbers, arrays, tensors and containers; else it cannot be known there."""
    from rl_utils.run import NOT_A_VALUE, value_before_loop

    def frame_of(**names):
        return types.SimpleNamespace(f_globals={"np": np, "torch": torch, "deque": collections.deque}, f_locals=names)

    def value(source, **names):
        return value_before_loop(ast.parse(source, mode="eval").body, frame_of(**names))

    seeds = types.SimpleNamespace(seeds=[1, 2])
    assert np.array_equal(value("np.zeros(len(run.seeds))", run=seeds), np.zeros(2))
    assert value("-np.inf") == -np.inf and value("args.noise * 2", args=types.SimpleNamespace(noise=0.1)) == 0.2
    assert value("deque(maxlen=3)") == collections.deque(maxlen=3)
    assert torch.equal(value("torch.full((2, 1), 0.1)"), torch.full((2, 1), 0.1))
    draws = np.random.get_state()[1].copy()
    for unknown in ("np.random.uniform(0.05, 0.15)", "envs.reset()", "np.zeros(len(obs))", "[x for x in range(2)]"):
        assert value(unknown, envs=None, obs=None) is NOT_A_VALUE, unknown
    assert np.array_equal(np.random.get_state()[1], draws)  # nothing drawn


def test_after_end_step_finds_the_first_statement_a_loop_runs_after_it():
    from rl_utils.run import after_end_step

    def last(run):
        for step in range(3):
            if step:
                run.log({}, step)
            run.end_step(step)

    def nested(run):
        for step in range(3):
            if step % 2:
                run.end_step(step)
                continue
            else:
                run.end_step(step)
                run.log({}, step)  # after it, in one branch

    def inner_function(run):
        def steps():
            for step in range(3):
                run.end_step(step)
                run.log({}, step)  # a loop of a function main defines: its own

        steps()

    def warm_up(run):
        for step in range(3):
            if step < 2:  # random actions: the step ends here
                run.end_step(step)
                continue
            run.log({}, step)  # the next step's
            run.end_step(step)

    def counted(run):
        step, left = 0, 3
        while step < 3:
            run.end_step(step)
            step += 1  # the loop's counters
            left -= 1

    def finally_after(run):
        for step in range(3):
            try:
                run.end_step(step)
            finally:
                run.log({}, step)

    def decayed(run):
        noise = 0.1
        for step in range(3):
            run.end_step(step)
            noise += 0.001  # the next step's annealing: a run resumed from the checkpoint would not make it

    for fine in (last, inner_function, warm_up, counted):
        assert after_end_step(fine.__code__) is None, fine.__name__
    assert after_end_step(decayed.__code__) == decayed.__code__.co_firstlineno + 4
    assert after_end_step(nested.__code__) == nested.__code__.co_firstlineno + 7
    assert after_end_step(finally_after.__code__) == finally_after.__code__.co_firstlineno + 5


def test_after_end_step_reads_a_script_whose_loop_is_at_module_level(tmp_path):
    """CleanRL's scripts have no main: their loop is the module's."""
    from rl_utils.run import after_end_step

    path = tmp_path / "flat_continuous_action.py"
    path.write_text("import os\nfor step in range(3):\n    run.end_step(step)\n    os.sep\n")
    assert after_end_step(compile(path.read_text(), str(path), "exec")) == 4
    path.write_text("import os\nfor step in range(3):\n    os.sep\n    run.end_step(step)\n")
    assert after_end_step(compile(path.read_text(), str(path), "exec")) is None


def test_with_several_seeds_a_network_not_built_by_stack_seeds_is_refused(run_of):
    """A bonus model built in plain PyTorch beside stacked networks is one network for every seed: it would train on
    all the seeds' data, and a checkpoint would cut its weights as if stacked. Refused at the start; one seed's is
    fine."""
    run, envs = run_of(num_seeds=2)
    torch.manual_seed(1)
    (actor,) = stack_seeds(lambda: [nn.Linear(3, 1)], run.seeds, CPU)
    bonus = nn.Sequential(nn.Linear(3, 8), nn.Linear(8, 1))
    with pytest.raises(SystemExit) as refused:
        run.start(envs, CPU, {"actor": actor, "bonus": bonus}, {})
    assert str(refused.value) == (
        "error: `bonus` (Sequential) is not stacked for the 2 seeds (a parameter [8, 3]): one network would train on "
        "every seed's data; build it with stack_seeds, in networks() or a call of its own, which gives each seed its own "
        "weights"
    )
    del actor
    run, envs = run_of(num_seeds=1)
    run.start(envs, CPU, {"bonus": bonus}, {})
    run.logs.close()


def test_a_grad_scaler_is_refused_with_several_seeds(run_of):
    """One loss scale for every seed, and one seed's overflow skipping every seed's step; one disabled (the
    enabled=args.fp16 pattern) does nothing."""
    scaler = torch.amp.GradScaler("cpu", enabled=False)
    run, envs = run_of(num_seeds=2)
    run.start(envs, CPU, {}, {}, scaler=scaler)
    run.logs.close()
    scaler = torch.amp.GradScaler("cpu")
    run, envs = run_of(num_seeds=2)
    with pytest.raises(SystemExit, match=r"`scaler` \(GradScaler\) keeps one loss scale for every seed.*--num-seeds 1"):
        run.start(envs, CPU, {}, {})
    run, envs = run_of(num_seeds=1)
    run.start(envs, CPU, {}, {}, scaler=scaler)
    run.logs.close()


def test_a_later_stack_seeds_build_draws_each_seeds_networks_anew_and_reproducibly():
    """Main's first build gives seed k a single-seed run's initial weights; a later one (a predictor beside its
    target, a reset's fresh networks) draws anew for each seed, as a single-seed run's later build does, from the
    process's generator: the same again after the same seeding. A non-network from networks() is refused."""

    def build():
        torch.manual_seed(4)
        return [stack_seeds(lambda: [nn.Linear(3, 2)], [4, 5, 6], CPU)[0].weight.detach().clone() for _ in range(3)]

    first, second, third = build()
    for k, seed in enumerate([4, 5, 6]):
        torch.manual_seed(seed)
        assert torch.equal(first[k], nn.Linear(3, 2).weight)
    for k in range(3):
        assert not torch.equal(second[k], first[k]) and not torch.equal(third[k], second[k])
    assert not torch.equal(second[0], second[1])
    assert all(torch.equal(a, b) for a, b in zip([first, second, third], build()))
    with pytest.raises(TypeError, match=r"^stack_seeds: networks\(\) returned a Parameter \(item 1\), not a network"):
        stack_seeds(lambda: [nn.Linear(3, 2), nn.Parameter(torch.zeros(1))], [4, 5], CPU)


class ObsStats:
    """A running normaliser whose state is NumPy's: --resume's safe loading cannot read it."""

    def __init__(self):
        self.mean = np.zeros(3)

    def state_dict(self):
        return {"mean": self.mean}

    def load_state_dict(self, state):
        self.mean = state["mean"]


def test_a_checkpoint_resume_could_not_load_is_refused_when_written(run_of, tmp_path):
    """A part whose state holds a NumPy array (or a flag holding an Enum) would be written without complaint and
    refused at --resume, hours later: the first checkpoint stops the run instead, naming it, and leaves no file."""
    run, envs = run_of(checkpoint_frequency=2, total_timesteps=10)
    run.start(envs, CPU, {}, {}, obs_stats=ObsStats())
    run.end_step(0)
    with pytest.raises(SystemExit) as refused:
        run.end_step(1)
    assert str(refused.value).startswith(
        "error: run.start's part `obs_stats`, at ['mean'], holds a numpy.ndarray, which --resume's safe loading "
        "(torch.load(weights_only=True)) refuses"
    )
    assert not list((tmp_path / "runs" / "r1").glob("checkpoint.pt*"))
    run.logs.close()

    for state, said in [
        ({"args": {"seed": 1, "modes": [Mode.FAST]}}, "the flag `modes` holds a test_forking.Mode"),
        ({"args": {}, "stats": {"n": np.float64(2.0)}}, "run.start's part `stats`, at ['n'], holds a numpy.float64"),
    ]:
        torch.save(state, tmp_path / "c.pt")
        with pytest.raises(SystemExit, match=re.escape(f"error: {said}, which --resume's safe loading")):
            ckpt.check_loadable(str(tmp_path / "c.pt"), state)


class Mode(enum.Enum):
    """A flag's type a fork might give its Args."""

    FAST = 1


class Prioritized(ReplayBuffer):
    """A prioritised replay buffer as a fork writes one: a subclass with state of its own."""

    def __init__(self, *args):
        super().__init__(*args)
        self.priorities = torch.zeros(self.num_seeds, self.capacity)
        self.max_priority = 1.0
        self.visits = np.zeros((self.num_seeds, self.capacity), dtype=np.int64)
        self.alpha, self.device = 0.6, CPU  # settings a checkpoint can hold too


class WithATree(Prioritized):
    """A subclass holding what a checkpoint cannot (a sum tree of its own class), with its own state_dict."""

    def __init__(self, *args):
        super().__init__(*args)
        self.tree = types.SimpleNamespace(total=0.0)

    def state_dict(self):
        return {**super().state_dict(), "tree_total": self.tree.total}

    def load_state_dict(self, state):
        super().load_state_dict(state)
        self.tree.total = state["tree_total"]


@pytest.mark.parametrize("num_seeds", [1, 2])
def test_a_replay_buffer_subclasss_own_state_goes_through_a_checkpoint(num_seeds, tmp_path):
    """Its priorities, largest priority and an array of its own go into each seed's checkpoint (safely loadable) and
    come back on resume (a NumPy number as a number); an attribute a checkpoint cannot hold is refused in one line,
    unless the subclass writes its own state_dict."""
    rb = Prioritized(8, 3, 1, num_seeds, CPU)
    for t in range(5):
        rb.add(
            np.full((num_seeds, 3), t, np.float32),
            np.ones((num_seeds, 3)),
            np.zeros((num_seeds, 1)),
            [1.0] * num_seeds,
            [0.0] * num_seeds,
        )
        rb.priorities[:, t] = torch.arange(num_seeds) + t
        rb.visits[:, t] = t
    rb.max_priority = np.float32(7.5)  # an array's max()
    parts = {"buffer": rb}
    state = {"buffer": rb.state_dict()}
    shares = split_seeds(
        {**state, "nets": {}, "optimizers": {}, "envs": [None] * num_seeds}, parts, [[]] * num_seeds, ["a", "b"][:num_seeds]
    )
    for k, share in enumerate(shares):
        torch.save(share, tmp_path / f"{k}.pt")
    loaded = [torch.load(tmp_path / f"{k}.pt", weights_only=True) for k in range(num_seeds)]
    resumed = Prioritized(8, 3, 1, num_seeds, CPU)
    resumed.load_state_dict(join_seeds(loaded, parts)["buffer"])
    assert torch.equal(resumed.priorities, rb.priorities) and resumed.max_priority == 7.5
    assert np.array_equal(resumed.visits, rb.visits) and resumed.visits.dtype == np.int64
    assert torch.equal(resumed.storage, rb.storage) and (resumed.pos, resumed.size) == (5, 5)
    rb.sum_tree = object()
    with pytest.raises(TypeError, match=r"^Prioritized.sum_tree is a object, which a checkpoint of the buffer cannot hold"):
        rb.state_dict()
    treed = WithATree(8, 3, 1, num_seeds, CPU)
    treed.tree.total = 3.0
    again = WithATree(8, 3, 1, num_seeds, CPU)
    again.load_state_dict(torch.load(io_of(treed.state_dict()), weights_only=True))
    assert again.tree.total == 3.0 and isinstance(again.tree, types.SimpleNamespace)


def io_of(state):
    """A state as torch.save writes it, to load back."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return buffer


class Scale(nn.Module):
    def __init__(self):
        super().__init__()
        self.fc = nn.Linear(3, 2)

    def forward(self, x, scale=1.0, *, shift):
        return self.fc(x) * scale + shift


@pytest.mark.parametrize("seeds", [[4], [4, 5, 6]], ids=["one seed", "three seeds"])
def test_per_seed_takes_keywords_and_cuts_tensors_in_lists_and_dicts(seeds):
    """Arguments by keyword are taken as by position (their tensors cut per seed, their networks swapped); tensors in
    a dict or a list are cut per seed as in a tuple; a NamedTuple's number, and an object holding a tensor the seeds
    share, are the seeds' own. A keyword-only tensor, and with several seeds an object holding each seed's tensor,
    which per_seed would not cut, stop in one line."""
    torch.manual_seed(seeds[0])
    (net,) = stack_seeds(lambda: [Scale()], seeds, CPU)
    x = torch.randn(len(seeds), 5, 3)

    def fn(batch, net, scale):
        return net(batch["x"], scale, shift=batch["extra"][0])

    expected = per_seed(lambda x, shift, net: net(x, 2.0, shift=shift))(x, x[..., :1], net)
    assert torch.equal(per_seed(fn)({"x": x, "extra": [x[..., :1]]}, net, 2.0), expected)
    assert torch.equal(per_seed(fn)(scale=2.0, net=net, batch={"x": x, "extra": [x[..., :1]]}), expected)
    assert torch.equal(per_seed(net)(x, 2.0, shift=1.0), per_seed(lambda x, net: net(x, 2.0, shift=1.0))(x, net))

    class Pair(typing.NamedTuple):
        x: torch.Tensor
        scale: float

    assert torch.equal(
        per_seed(lambda p, net: net(p.x, p.scale, shift=0.0))(Pair(x, 2.0), net), per_seed(net)(x, 2.0, shift=0.0)
    )
    with pytest.raises(TypeError, match=r"^per_seed\(Scale\): its keyword-only argument `shift` holds a tensor"):
        per_seed(net)(x, shift=x[..., :1])

    def with_default(x, scale=2.0, net=None):  # a default skipped, the network by keyword
        return net(x, scale, shift=0.0)

    assert torch.equal(per_seed(with_default)(x, net=net), per_seed(net)(x, 2.0, shift=0.0))

    @dataclasses.dataclass
    class Holder:
        x: torch.Tensor

    shared = Holder(torch.ones(2))  # a tensor the seeds share, in an object: passed whole
    assert torch.equal(per_seed(lambda x, h, net: net(x, shift=0.0) * h.x)(x, shared, net), per_seed(net)(x, shift=0.0))
    if len(seeds) > 1:  # each seed's tensor in an object, which per_seed would not cut
        with pytest.raises(TypeError, match=r"^per_seed\(<lambda>\): argument 1 is a Holder holding `x`, a tensor \[3, "):
            per_seed(lambda h, net: net(h.x, shift=0.0))(Holder(x), net)


def test_what_run_log_and_run_evaluate_cannot_take_stops_in_one_line(run_of):
    """A tensor of a batch's values logged with one seed, a NaN logged outside run.stop_on_nan (inside, it ends the
    run), returns that are not [num_seeds, episodes], and a second evaluation at one step."""
    run, envs = run_of()
    run.start(envs, CPU, {}, {})
    with pytest.raises(ValueError, match=r"^run.log: `losses/q` has 64 values \(shape \[64\]\): log one number per seed"):
        run.log({"losses/q": torch.zeros(64)}, 0)
    with pytest.raises(FloatingPointError, match=r"^run.log: `losses/action_std` is not finite at step 0"):
        run.log({"losses/action_std": torch.tensor([float("nan")])}, 0)
    with pytest.raises(SystemExit, match="action_std became non-finite at step 0"):
        with run.stop_on_nan(0):
            run.log({"losses/action_std": torch.tensor([float("nan")])}, 0)
    with pytest.raises(ValueError, match=re.escape("run.evaluate: returns of shape [10] for 1 seed(s): one row")):
        run.evaluate(0, np.zeros(10))
    run.evaluate(0, np.zeros((1, 10)))
    with pytest.raises(ValueError, match=r"^run.evaluate: a second evaluation at step 0"):
        run.evaluate(0, np.ones((1, 10)))
    run.logs.close()


def test_torch_distributions_draws_and_torch_compile_with_several_seeds_stop_in_one_line():
    """Normal(...).rsample() in a per-seed function draws into a tensor of its own, which a vmap cannot give each
    seed: the stop names the rewrite. A per-seed function under torch.compile stops saying what to do instead."""
    torch.manual_seed(4)
    (net,) = stack_seeds(lambda: [nn.Linear(3, 2)], [4, 5, 6], CPU)
    x = torch.randn(3, 5, 3)
    with pytest.raises(RuntimeError, match=re.escape("write mean + std * torch.randn_like(mean)")):
        per_seed(lambda x, net: torch.distributions.Normal(net(x), 1.0).rsample())(x, net)
    with pytest.raises(RuntimeError, match=r"^per_seed\(<lambda>\) with 3 seeds under torch.compile: .*--cudagraphs"):
        torch.compile(lambda x: per_seed(lambda x, net: net(x))(x, net), backend="eager")(x)


def test_save_model_cuts_an_objects_state_per_seed():
    """--save-model of an object with a state (running statistics [num_seeds, ...]) gives each seed its own share."""
    stats = types.SimpleNamespace(state_dict=lambda: {"mean": torch.arange(6.0).view(3, 2), "count": 4})
    saved = [model_of_seed({"stats": stats}, k, 3)["stats"] for k in range(3)]
    assert [s["mean"].tolist() for s in saved] == [[[0.0, 1.0]], [[2.0, 3.0]], [[4.0, 5.0]]]
    assert all(s["count"] == 4 for s in saved)


@pytest.mark.parametrize("num_seeds", [1, 2])
def test_a_normalised_next_obs_made_from_the_next_episodes_first_observation_stops_at_the_next_add(num_seeds):
    """A fork that stores normalised observations, (x - mean) / std, computed from envs.step's next_obs: where the
    time limit cut an episode, the row stored is the next episode's first observation, normalised, which no value
    check finds; it is the next add's obs, so that add stops, naming the seed and the fix. Normalised from
    infos["real_next_obs"], the same run stores every step."""
    mean, std = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.6, 0.7])

    def run(from_real: bool, steps=210):
        envs = SeedEnvs("Pendulum-v1", [1, 2][:num_seeds])
        rb = ReplayBuffer(300, envs.obs_dim, envs.action_dim, num_seeds, CPU)
        obs = (envs.reset() - mean) / std
        for _ in range(steps):
            next_obs, rewards, terminations, truncations, infos = envs.step(envs.sample_actions())
            stored = (infos["real_next_obs"] if from_real else next_obs) - mean
            rb.add(obs, stored / std, envs.sample_actions(), rewards, terminations)
            obs = (next_obs - mean) / std
        envs.close()
        return rb

    assert run(from_real=True).size == 210
    with pytest.raises(ValueError) as refused:
        run(from_real=False)
    assert str(refused.value).startswith(
        "ReplayBuffer.add: the next_obs stored for seed index 0 where its episode ended (the add before this one) is "
        "this add's obs, made from the next episode's first observation"
    )
    assert refused.traceback[-1].locals.get("self").size == 200  # the add of step 200, right after the cut at step 199


def test_correct_loops_that_store_past_an_episode_end_are_not_refused_by_the_next_add_check():
    """The check of a normalised next_obs reads the latest envs.step's record: it holds only for an add of that step's
    transition. A transition added a step late, a second loop's envs stepped between (its episode ending), an
    evaluation's SeedEnvs stepped between the step and the add, and observations that carry nothing (all zeros)
    store every step."""
    steps = 410  # past the time limit's cuts at steps 199 and 399

    def a_loop(envs):
        obs = envs.reset()
        while True:
            next_obs, rewards, terminations, _, infos = envs.step(envs.sample_actions())
            yield obs, np.asarray(infos["real_next_obs"]), envs.sample_actions(), rewards, terminations
            obs = next_obs

    def buffer():
        return ReplayBuffer(steps, 3, 1, 1, CPU)

    late, pending, envs = buffer(), None, SeedEnvs("Pendulum-v1", [1])
    for transition, _ in zip(a_loop(envs), range(steps)):
        if pending is not None:
            late.add(*pending)  # a step late
        pending = transition
    first, second = buffer(), buffer()
    first_loop, second_loop = a_loop(SeedEnvs("Pendulum-v1", [1])), a_loop(SeedEnvs("Pendulum-v1", [2]))
    for _ in range(50):
        next(first_loop)  # the second loop's episodes end 50 steps after the first's
    for _ in range(steps - 50):
        one, two = next(first_loop), next(second_loop)
        first.add(*one)
        second.add(*two)
    evaluated, evaluation = buffer(), SeedEnvs("Pendulum-v1", [101])
    for t, transition in zip(range(steps), a_loop(SeedEnvs("Pendulum-v1", [1]))):
        if t % 150 == 0:  # a whole evaluation episode between the step and the add
            evaluation.reset()
            for _ in range(200):
                evaluation.step(evaluation.sample_actions())
        evaluated.add(*transition)
    blind = buffer()
    for transition, _ in zip(a_loop(SeedEnvs("Pendulum-v1", [1])), range(steps)):
        obs, next_obs, actions, rewards, terminations = transition
        blind.add(np.zeros_like(obs), np.zeros_like(next_obs), actions, rewards, terminations)
    assert [rb.size for rb in (late, first, second, evaluated, blind)] == [steps - 1, steps - 50, steps - 50, steps, steps]


@pytest.mark.parametrize("num_seeds", [1, 2])
def test_terminations_or_truncations_stored_with_normalised_observations_stop_at_the_time_limit(num_seeds):
    """The mark that finds `terminations | truncations` does not follow computed (normalised) observations: the
    latest step's record does, at the add of the step the time limit cut (199); the mark, on infos["real_next_obs"]
    stored as it is. A fork that means it (rb.time_limits_end_episodes) stores either."""
    mean, std = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.6, 0.7])

    def run(means_it=False, normalised=True, steps=210):
        envs = SeedEnvs("Pendulum-v1", [1, 2][:num_seeds])
        rb = ReplayBuffer(300, envs.obs_dim, envs.action_dim, num_seeds, CPU)
        rb.time_limits_end_episodes = means_it
        obs = envs.reset()
        for _ in range(steps):
            next_obs, rewards, terminations, truncations, infos = envs.step(envs.sample_actions())
            real = infos["real_next_obs"]
            stored = (real - mean) / std if normalised else real
            rb.add(obs, stored, envs.sample_actions(), rewards, terminations | truncations)
            obs = next_obs
        envs.close()
        return rb

    for normalised in (True, False):
        with pytest.raises(ValueError) as refused:
            run(normalised=normalised)
        assert str(refused.value).startswith(
            "ReplayBuffer.add: terminations is 1 for seed index 0, whose episode its time limit cut (truncated, not "
            "terminated)"
        )
        assert str(refused.value).endswith("a time limit to end its episodes sets rb.time_limits_end_episodes = True)")
        assert not normalised or refused.traceback[-1].locals["self"].size == 199  # at the add of step 199
        assert run(means_it=True, normalised=normalised).size == 210
