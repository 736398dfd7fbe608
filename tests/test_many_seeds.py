"""--num-seeds: several seeds trained side by side in one process, their networks stacked (rl_utils.stack_seeds) and
the scripts' one-seed functions run for all of them at once (rl_utils.per_seed, torch.func.vmap). The seeds must stay
independent runs (nothing one seed sees reaches another), each seed's update must be the one-seed update with its
loss summed, not averaged, into the total, and each seed must be an ordinary run to every tool: its own folder,
evaluations, checkpoint, resume and saved model."""

import copy
import dataclasses
import importlib
import os
import random
import signal
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn as nn

from conftest import (
    OFF_POLICY,
    QUICK,
    REPO,
    declared,
    SCRIPTS,
    cli_flags,
    load,
    refusal,
    scalars,
    script_command,
    small_args,
    source,
)
import forkserver
from rl_utils import SeedEnvs, evaluate, per_seed, stack_seeds
from rl_utils.seeds import split_seeds
from rl_utils import checkpoints as ckpt
from rl_utils.cli import validate

sys.path.insert(0, os.path.join(REPO, "tools"))
import evaluate as evaluate_tool  # noqa: E402


def accepts_many_seeds(script) -> bool:
    module = load(script)
    if "num_seeds" not in {f.name for f in dataclasses.fields(module.Args)}:
        return False
    args = module.Args(num_seeds=2)
    try:
        validate(args, module.check_args(args) if hasattr(module, "check_args") else [])
    except SystemExit:
        return False
    return True


MANY_SEEDS = [script for script in SCRIPTS if accepts_many_seeds(script)]
ENV = "dm_control/cartpole-swingup-v0"


def test_the_paper_algorithms_train_many_seeds():
    assert {"td3", "oparl", "sac", "redq"} <= set(MANY_SEEDS)


# per_seed itself, on a toy network
class Toy(nn.Module):
    def __init__(self):
        super().__init__()
        self.fc = nn.Linear(3, 2)

    def forward(self, x):
        return self.fc(x)


def toy_loss(x, net: Toy, scale: float):
    return (net(x) * scale).pow(2).mean(), net(x)


def test_per_seed_with_one_seed_runs_the_function_as_written():
    torch.manual_seed(0)
    (net,) = stack_seeds(lambda: [Toy()], [7], torch.device("cpu"))
    assert net.fc.weight.shape == (2, 3)  # not stacked: the module as built
    x = torch.randn(1, 5, 3)
    loss, out = per_seed(toy_loss)(x, net, 2.0)
    expected_loss, expected_out = toy_loss(x[0], net, 2.0)
    assert loss.shape == (1,) and torch.equal(loss[0], expected_loss) and torch.equal(out[0], expected_out)


def test_per_seed_gives_each_seed_its_own_function_value_and_gradient_under_a_sum():
    torch.manual_seed(4)  # as main seeds the process before its first build
    (stacked,) = stack_seeds(lambda: [Toy()], [4, 5, 6], torch.device("cpu"))
    assert stacked.fc.weight.shape == (3, 2, 3)
    x = torch.randn(3, 5, 3)
    loss, _ = per_seed(toy_loss)(x, stacked, 2.0)
    loss.sum().backward()
    for k, seed in enumerate([4, 5, 6]):
        torch.manual_seed(seed)
        alone = Toy()  # seed k's initial weights are a single-seed run's
        assert torch.equal(alone.fc.weight, stacked.fc.weight[k].detach())
        alone_loss, _ = toy_loss(x[k], alone, 2.0)
        alone_loss.backward()
        torch.testing.assert_close(loss[k], alone_loss)
        torch.testing.assert_close(stacked.fc.weight.grad[k], alone.fc.weight.grad)  # a mean over seeds: a third


def test_per_seed_draws_differently_for_each_seed_and_reproducibly():
    noisy = per_seed(lambda x: x + torch.randn_like(x))
    x = torch.zeros(3, 1000)
    torch.manual_seed(0)
    first = noisy(x)
    assert not torch.equal(first[0], first[1]) and not torch.equal(first[1], first[2])
    assert abs(float(torch.corrcoef(first[:2])[0, 1])) < 0.1
    torch.manual_seed(0)
    assert torch.equal(noisy(x), first)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """main's result after a short run, per (script, num_seeds), made once per test process."""
    cache = {}

    def get(script, num_seeds):
        if (script, num_seeds) not in cache:
            module = load(script)
            cwd = os.getcwd()
            os.chdir(tmp_path_factory.mktemp(f"{script}{num_seeds}"))
            try:
                args = small_args(module, env_id=ENV, num_seeds=num_seeds, total_timesteps=400, eval_frequency=400)
                args.run_name = "run{seed}"
                cache[script, num_seeds] = module.main(args)
            finally:
                os.chdir(cwd)
        return cache[script, num_seeds]

    return get


def modules(result) -> dict:
    """The networks in main's result, each once (OPARL returns its pessimistic actor also as "actor")."""
    found = {}
    for name, net in result.items():
        if isinstance(net, nn.Module) and all(net is not other for other in found.values()):
            found[name] = net
    return found


def optimizers(result) -> dict:
    return {k: v for k, v in result.items() if isinstance(v, torch.optim.Optimizer)}


def tensor_parts(result) -> dict:
    """The tensors main trains outside its networks (SAC's log_alpha), by the checkpoint's name for them."""
    return {"log_alpha": result["a_optimizer"].param_groups[0]["params"][0]} if "a_optimizer" in result else {}


def stacked_state(result) -> dict:
    """Copies of every network's, optimizer's and tensor's state in main's result, and of the global generator's."""
    tensors = [t for t in result.values() if isinstance(t, torch.Tensor)] + list(tensor_parts(result).values())
    return {
        "nets": copy.deepcopy({k: n.state_dict() for k, n in modules(result).items()}),
        "opt": copy.deepcopy({k: o.state_dict() for k, o in optimizers(result).items()}),
        "tensors": [(t, t.detach().clone()) for t in tensors],
        "rng": torch.get_rng_state(),
    }


def load_state(result, state):
    for name, sd in state["nets"].items():
        result[name].load_state_dict(sd)
    for name, sd in state["opt"].items():
        result[name].load_state_dict(copy.deepcopy(sd))
    with torch.no_grad():
        for tensor, value in state["tensors"]:
            tensor.copy_(value)
    torch.set_rng_state(state["rng"])


def one_update(result, batch):
    """One training iteration through main's own update, with every optional part on (policy step, target step)."""
    flags = result["update"].__code__.co_argcount - 1
    return result["update"](batch, *[True] * flags)


def step_batches(script, rb, size=64):
    """What a training step's update takes: a batch per seed [num_seeds, size, ...], or REDQ's --utd-ratio of them
    ([num_seeds, G, size, ...]), as short_run's settings give it."""
    utd_ratio = (declared(QUICK, script) or {}).get("utd_ratio")
    return rb.sample(*([utd_ratio] if utd_ratio else []), size)


def params(result) -> dict:
    """Every network's parameters in main's result, by network and parameter name."""
    return {f"{name}.{p}": t for name, net in modules(result).items() for p, t in net.named_parameters()}


def seed_params(result, k) -> dict:
    """Seed k's cut of every (stacked) network's parameters."""
    return {name: t[k] for name, t in params(result).items()}


@pytest.mark.parametrize("script", [pytest.param(s, marks=pytest.mark.xdist_group(f"many-{s}")) for s in MANY_SEEDS])
def test_changing_one_seeds_data_and_weights_leaves_the_others_bit_identical(script, short_run):
    result = short_run(script, 3)
    batch = step_batches(script, result["rb"])
    before = stacked_state(result)
    one_update(result, batch)
    reference = {k: [t.clone() for t in seed_params(result, k).values()] for k in range(3)}

    load_state(result, before)  # the same draws again
    with torch.no_grad():  # seed 1 (index 0) gets other weights and other data
        for net in modules(result).values():
            for p in net.parameters():
                p[0].mul_(1.5)
    changed = type(batch)(*(field.clone() for field in batch))
    changed.rewards[0] += 10.0
    changed.observations[0] *= -1
    one_update(result, changed)
    for k in (1, 2):
        for name, a, b in zip(seed_params(result, k), reference[k], seed_params(result, k).values()):
            assert torch.equal(a, b), f"seed index {k}'s {name} changed with seed index 0's data"
    assert any(not torch.equal(a, b) for a, b in zip(reference[0], seed_params(result, 0).values()))
    load_state(result, before)  # the shared run as it was, for the other tests


@pytest.mark.parametrize("script", [pytest.param(s, marks=pytest.mark.xdist_group(f"many-{s}")) for s in MANY_SEEDS])
def test_a_seeds_update_is_the_one_seed_update_on_the_same_batch(script, short_run, monkeypatch):
    """With the noise taken out (every torch.randn_like a zero), seed 3 of 3 updates exactly as a one-seed run in
    seed 3's state does on seed 3's batch: the weights, and the gradients (a mean over seeds would give a third)."""
    many, one = short_run(script, 3), short_run(script, 1)
    before_many, before_one = stacked_state(many), stacked_state(one)
    nets, opts = modules(many), optimizers(many)
    parts = {"buffer": many["rb"], **tensor_parts(many)}
    state = ckpt.snapshot(f"{script}_continuous_action.py", load(script).Args(), [], 0, nets, opts, parts)
    share = split_seeds(state, parts, [[], [], []], ["a", "b", "c"])[2]  # seed index 2, as a checkpoint
    one_parts = {"buffer": one["rb"], **tensor_parts(one)}
    ckpt.restore(share, [], {k: one[k] for k in nets}, {k: one[k] for k in opts}, one_parts)
    if "alpha" in many:  # SAC's entropy coefficient follows log_alpha
        with torch.no_grad():
            one["alpha"].copy_(many["alpha"][2:3])

    monkeypatch.setattr(torch, "randn_like", torch.zeros_like)
    monkeypatch.setattr(torch, "randperm", lambda n, **kw: torch.arange(n, **kw))  # REDQ's target subsets: the same
    batch = step_batches(script, many["rb"])
    restored_many, restored_one = stacked_state(many), stacked_state(one)
    # The critics' weights and gradients from one update; then, from the same state, the actors' with the critics
    # keeping their weights (learning rate 0), so that they are taken through the same critics: critics updated apart
    # differ by up to an Adam step where a gradient is near zero (rounding flips its sign), enough to change which of
    # OPARL's critics is a sample's max.
    for critics in (True, False):
        if not critics:
            load_state(many, restored_many)
            load_state(one, restored_one)
            for result in (many, one):
                for group in result["q_optimizer"].param_groups:
                    group["lr"] = 0.0
        one_update(many, batch)
        one_update(one, type(batch)(*(field[2:3] for field in batch)))
        checked = 0
        for (name, p_many), p_one in zip(params(many).items(), params(one).values()):
            if name.startswith("qf.") != critics:
                continue
            # to a third of an Adam step (lr 3e-4): where a gradient is near zero, rounding can flip the sign of a step
            torch.testing.assert_close(p_one, p_many[2], rtol=1e-4, atol=1e-4, msg=f"{name}: seed 3 of 3 against it alone")
            # the gradients too: a mean over seeds instead of the sum would make them a third (a difference the weights
            # hide, as Adam divides by the gradients' scale); the critics' agree to rounding (REDQ's, its last of
            # several critic updates a step, to 9e-4 with 2), the actors' to a few thousandths
            if p_one.grad is not None:
                error = (p_many.grad[2] - p_one.grad).abs().max() / p_one.grad.abs().max()
                tolerance = (1e-2 if script == "redq" else 1e-4) if critics else 5e-2
                assert error < tolerance, f"{name}'s gradient differs by {error:.1e}"
                checked += 1
        assert checked
    load_state(many, before_many)
    load_state(one, before_one)


class PerturbedSeedEnvs(SeedEnvs):
    """SeedEnvs whose second env has another seed and offset rewards: another seed's data and episode ends (Hopper's
    random-phase episodes end at other steps), from the environment on."""

    def __init__(self, env_id: str, seeds: list, *args, **kwargs):
        super().__init__(env_id, [s + 50 if len(seeds) == 3 and k == 1 else s for k, s in enumerate(seeds)], *args, **kwargs)

    def step(self, actions):
        next_obs, rewards, terminations, truncations, infos = super().step(actions)
        if len(rewards) == 3:
            rewards = rewards.copy()
            rewards[1] += 5.0
        return next_obs, rewards, terminations, truncations, infos


def plain_and_perturbed(module, script: str, monkeypatch) -> tuple:
    """A 3-seed process's results, as it is and with PerturbedSeedEnvs (`module`: the script, or a fork of it held to
    the script's settings)."""
    args = {"env_id": "Hopper-v4", "total_timesteps": 360, "learning_starts": 300, "eval_frequency": 120}
    args |= {"checkpoint_frequency": 50, "num_seeds": 3}
    if script == "oparl":
        args["reset_frequency"] = 25  # two resets (iterations 25 and 50) of every seed's optimistic actor at once

    def parsed(**values):
        return module.Args(**vars(small_args(load(script), **args, **values)))

    plain = module.main(parsed(run_name="plain{seed}"))
    monkeypatch.setattr(module, "SeedEnvs", PerturbedSeedEnvs)
    return plain, module.main(parsed(run_name="perturbed{seed}"))


@pytest.mark.slow
@pytest.mark.parametrize("script", MANY_SEEDS)
def test_another_seeds_environment_leaves_a_seeds_whole_run_bit_identical(script, tmp_path, monkeypatch):
    """The whole loop, not one update: a 3-seed process whose second seed sees other rewards and episode ends gives the
    first and the third seed the same replay buffer, weights and evaluations bit for bit, through evaluations,
    checkpoints and (for OPARL) parameter resets, on Hopper, whose seeds' episodes end at different steps."""
    monkeypatch.chdir(tmp_path)
    plain, perturbed = plain_and_perturbed(load(script), script, monkeypatch)
    assert not torch.equal(plain["rb"].storage[1], perturbed["rb"].storage[1])  # seed index 1 did see other data
    for k in (0, 2):
        assert torch.equal(plain["rb"].storage[k], perturbed["rb"].storage[k])
        for (name, a), b in zip(seed_params(plain, k).items(), seed_params(perturbed, k).values()):
            assert torch.equal(a, b), f"seed index {k}'s {name}"
        assert plain["seeds_eval_returns"][k] == perturbed["seeds_eval_returns"][k]
    assert [s for s, _ in plain["seeds_eval_returns"][2]] == [0, 120, 240, 360]


@pytest.mark.slow
def test_updates_timed_by_any_seeds_episode_end_reach_the_other_seeds(tmp_path, monkeypatch):
    """What the whole-run test above catches in a fork: TD3's original extra updates as an episode ends, timed by any
    seed's end (`ended.any()`), change the first seed's weights when only the second seed's env changed."""
    anchor = "        run.end_step(global_step)  # training speed"
    extra = "        if global_step >= args.learning_starts and (terminations | truncations).any():\n"
    extra += "            update(rb.sample(args.batch_size), True)\n"
    td3 = source("td3")
    assert anchor in td3
    (tmp_path / "anyend_continuous_action.py").write_text(td3.replace(anchor, extra + anchor))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    fork = importlib.import_module("anyend_continuous_action")
    plain, perturbed = plain_and_perturbed(fork, "td3", monkeypatch)
    assert not all(torch.equal(a, b) for a, b in zip(seed_params(plain, 0).values(), seed_params(perturbed, 0).values()))


@pytest.mark.parametrize("script", MANY_SEEDS)
def test_a_seeds_initial_weights_are_those_of_a_single_seed_run_bit_for_bit(script):
    module = load(script)
    space = gym.spaces.Box(-np.ones(2, np.float32), np.ones(2, np.float32))

    def networks():
        critics = [module.QEnsemble(5, 2)] + ([module.QEnsemble(5, 2, style="td3")] if script == "oparl" else [])
        return [module.Actor(5, space), *critics]

    torch.manual_seed(4)  # as main seeds the process before its first build
    stacked = stack_seeds(networks, [4, 5, 6], torch.device("cpu"))
    torch.manual_seed(5)
    for net, alone in zip(stacked, networks()):
        for (name, p), q in zip(net.named_parameters(), alone.parameters()):
            assert torch.equal(p[1], q), f"{type(alone).__name__}.{name}"


@pytest.mark.slow
@pytest.mark.parametrize("script", MANY_SEEDS)
def test_each_seed_is_an_ordinary_run(script, tmp_path):
    """Own folder, evaluation schedule and saved model; the saved actor is that seed's, a one-seed actor, and
    tools/evaluate.py evaluates it to its logged return; every seed learns its own weights."""
    module = load(script)
    flags = cli_flags(script, total_timesteps=600, learning_starts=300, batch_size=64, eval_frequency=300, eval_episodes=1)
    result = forkserver.run(  # Pendulum: short evaluation episodes
        script_command(
            script,
            "--env-id",
            "Pendulum-v1",
            *flags,
            "--seed",
            "4",
            "--num-seeds",
            "2",
            "--run-name",
            "r{seed}",
            "--save-model",
        ),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert sorted(os.listdir(tmp_path / "runs")) == ["r4", "r5"]
    envs = SeedEnvs("Pendulum-v1", [0])
    obs_dim, space = envs.obs_dim, envs.action_space
    actors = []
    for seed in (4, 5):
        run_dir = tmp_path / "runs" / f"r{seed}"
        logged = scalars(str(run_dir))["eval/episodic_return"]
        assert [step for step, _ in logged] == [0, 300, 600]
        model = str(run_dir / f"{script}_continuous_action.cleanrl_model")
        saved = torch.load(model, weights_only=True)
        module.Actor(obs_dim, space).load_state_dict(saved["actor"])  # a one-seed actor, as a single-seed run saves it
        assert "probe" in saved and "warning" not in result.stderr  # its probe: that seed's actions, which evaluate.py checks
        returns = evaluate_tool.main([model, "--env-id", "Pendulum-v1", "--seed", str(seed + 100), "--episodes", "1"])
        assert returns.mean() == pytest.approx(logged[-1][1], rel=1e-4)  # evaluated in training: to vmap's rounding
        actors.append(saved["actor"])
    assert any(not torch.equal(actors[0][k], actors[1][k]) for k in actors[0])


# (script, env): Hopper's seeds' episodes end at different steps, so the process resumes mid-episode in each env; SAC's
# log_alpha is the one trained tensor outside a network that a resume must cut and join per seed
KILL_CASES = [("sac", "Hopper-v4")]


@pytest.mark.slow
@pytest.mark.parametrize("script, env_id", [c for c in KILL_CASES if c[0] in MANY_SEEDS])
def test_a_killed_many_seed_process_resumes_identical(script, env_id, tmp_path):
    flags = cli_flags(script, total_timesteps=1200, learning_starts=500, batch_size=64, eval_frequency=600, eval_episodes=1)
    flags = ["--env-id", env_id, *flags, "--num-seeds", "2", "--save-model"]

    def start(name, *extra):
        log = open(tmp_path / f"{name}.log", "w")
        command = script_command(script, *flags, "--run-name", name + "{seed}", *extra)
        return forkserver.Popen(command, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT, fresh=name == "full")

    full, killed = start("full"), start("killed", "--checkpoint-frequency", "550")  # a new interpreter, and a fork
    checkpoints = [tmp_path / "runs" / f"killed{seed}" / "checkpoint.pt" for seed in (1, 2)]
    deadline = time.time() + 240
    while not all(c.exists() for c in checkpoints) and killed.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert all(c.exists() for c in checkpoints), (tmp_path / "killed.log").read_text()
    time.sleep(random.uniform(0.0, 1.0))
    killed.send_signal(signal.SIGKILL)
    assert killed.wait() == -signal.SIGKILL, "the run ended before the kill: the comparison would test nothing"
    killed_at = torch.load(checkpoints[0], weights_only=True)["global_step"]
    assert 500 < killed_at < 1200  # after the optimizers have stepped
    resumed = forkserver.run(
        script_command(script, "--resume", "runs/killed2", "--save-model"),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert full.wait(timeout=300) == 0
    for seed in (1, 2):
        full_dir, resumed_dir = tmp_path / "runs" / f"full{seed}", tmp_path / "runs" / f"killed{seed}"
        full_log, resumed_log = scalars(str(full_dir)), scalars(str(resumed_dir))
        assert resumed_log["eval/episodic_return"] == full_log["eval/episodic_return"]
        assert resumed_log["losses/qf_loss"] == full_log["losses/qf_loss"]
        model = f"{script}_continuous_action.cleanrl_model"
        a, b = (torch.load(d / model, weights_only=True)["actor"] for d in (full_dir, resumed_dir))
        assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def two_seed_run(tmp_path_factory):
    """A finished, checkpointed two-seed run of TD3 (or the first script that trains many seeds)."""
    cwd = tmp_path_factory.mktemp("two")
    script = MANY_SEEDS[0]
    flags = cli_flags(script, total_timesteps=400, learning_starts=200, batch_size=32, eval_frequency=400, eval_episodes=1)
    command = script_command(script, "--env-id", "Pendulum-v1", *flags, "--num-seeds", "2", "--run-name", "s{seed}")
    result = forkserver.run([*command, "--checkpoint-frequency", "200"], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return script, cwd


@pytest.mark.xdist_group("two-seed-run")
def test_a_kill_between_the_seeds_checkpoint_renames_is_finished_on_resume(two_seed_run, monkeypatch):
    script, cwd = two_seed_run
    name = f"{script}_continuous_action.py"
    monkeypatch.chdir(cwd)
    second = cwd / "runs" / "s2" / "checkpoint.pt"
    new = torch.load(second, weights_only=True)
    os.replace(second, str(second) + ".tmp")  # seed 2's new checkpoint written but not yet renamed ...
    torch.save({**new, "global_step": new["global_step"] - 100}, second)  # ... over its old one
    checkpoints = ckpt.load_checkpoints("runs/s1", name)
    assert [c["global_step"] for c in checkpoints] == [new["global_step"]] * 2
    assert torch.load(second, weights_only=True)["global_step"] == new["global_step"] and not os.path.exists(
        str(second) + ".tmp"
    )
    torch.save({**new, "global_step": new["global_step"] - 100}, second)  # old, and no new one beside it
    with pytest.raises(SystemExit, match="holds no checkpoint at step"):
        ckpt.load_checkpoints("runs/s1", name)
    torch.save(new, second)


@pytest.mark.xdist_group("two-seed-run")
def test_a_seeds_checkpoint_is_a_single_seed_checkpoint_in_form(two_seed_run):
    """Each seed's cut holds plain (unstacked) state dicts, its own buffer rows, env and evaluations."""
    script, cwd = two_seed_run
    one, two = (torch.load(cwd / "runs" / f"s{seed}" / "checkpoint.pt", weights_only=True) for seed in (1, 2))
    module = load(script)
    space = gym.spaces.Box(-np.ones(1, np.float32), 2 * np.ones(1, np.float32))
    actor = next(name for name in one["nets"] if name.endswith("actor"))  # OPARL's pessimistic one first
    for checkpoint in (one, two):
        module.Actor(3, space).load_state_dict(checkpoint["nets"][actor])  # Pendulum: 3 observations, 1 action
        assert checkpoint["buffer"]["rows"].shape[0] == 1 and len(checkpoint["envs"]) == 1
    assert not torch.equal(one["nets"][actor]["fc1.weight"], two["nets"][actor]["fc1.weight"])
    assert one["eval_returns"] != two["eval_returns"] and [one["seed_index"], two["seed_index"]] == [0, 1]


@pytest.mark.xdist_group("two-seed-run")
def test_bad_many_seed_input_is_one_line(two_seed_run, monkeypatch, tmp_path):
    script, cwd = two_seed_run
    assert "--num-seeds must be >= 1" in refusal(script, ["--num-seeds", "0"], tmp_path, monkeypatch)
    assert "write {seed}" in refusal(script, ["--num-seeds", "2", "--run-name", "same"], tmp_path, monkeypatch)
    assert "write {seed} in its last part" in refusal(
        script, ["--num-seeds", "2", "--run-name", "seed{seed}/run"], tmp_path, monkeypatch
    )  # two seeds' folders named alike would collide on resume
    assert "--track" in refusal(script, ["--num-seeds", "2", "--track"], tmp_path, monkeypatch)
    message = refusal(script, ["--resume", "runs/s1", "--num-seeds", "3"], cwd, monkeypatch)
    assert "--num-seeds 3 (run: 2)" in message
    assert "--seed 7 (run: 1)" in refusal(script, ["--resume", "runs/s2", "--seed", "7"], cwd, monkeypatch)
    for other in [s for s in OFF_POLICY if s not in MANY_SEEDS]:
        assert "--num-seeds" in refusal(other, ["--num-seeds", "2"], tmp_path, monkeypatch)


@pytest.mark.xdist_group("two-seed-run")
def test_older_checkpoints_are_refused_in_one_line(two_seed_run, monkeypatch, tmp_path):
    script, cwd = two_seed_run
    old = {k: v for k, v in torch.load(cwd / "runs" / "s1" / "checkpoint.pt", weights_only=True).items() if k != "format"}
    (tmp_path / "runs" / "old").mkdir(parents=True)
    torch.save(old, tmp_path / "runs" / "old" / "checkpoint.pt")
    assert "written by an older" in refusal(script, ["--resume", "runs/old"], tmp_path, monkeypatch)


@pytest.mark.parametrize("script", MANY_SEEDS)
def test_evaluation_draws_nothing(script):
    """Evaluation steps every seed's env until the last seed's episodes end (Hopper's end at different steps): a draw
    there would make one seed's training draws depend on the others' episodes (SAC evaluates its deterministic action)."""
    module = load(script)
    envs = SeedEnvs("Hopper-v4", [101, 102])
    (actor,) = stack_seeds(lambda: [module.Actor(envs.obs_dim, envs.action_space)], [1, 2], torch.device("cpu"))
    act = per_seed(actor.deterministic_action if hasattr(actor, "deterministic_action") else actor)
    before = torch.get_rng_state()
    returns = evaluate(lambda obs: act(torch.as_tensor(obs)).detach().numpy(), envs, [101, 102], 2)
    assert returns.shape == (2, 2)
    assert torch.equal(torch.get_rng_state(), before)


def test_each_seeds_batch_comes_from_its_own_transitions():
    from rl_utils import ReplayBuffer

    rb = ReplayBuffer(8, 2, 1, 3, torch.device("cpu"))
    for i in range(5):  # seed k's rows hold 100 k + i in every field
        rows = np.array([100.0 * k + i for k in range(3)])
        rb.add(np.stack([rows, rows], -1), np.stack([rows, rows], -1), rows[:, None], rows, rows * 0)
    batch = rb.sample(4, 50)
    assert batch.observations.shape == (3, 4, 50, 2) and batch.rewards.shape == (3, 4, 50)
    for k in range(3):
        seen = batch.rewards[k].unique()
        assert set(seen.tolist()) <= {100.0 * k + i for i in range(5)} and len(seen) > 1
        assert torch.equal(batch.observations[k, ..., 0], batch.rewards[k])
        assert torch.equal(batch.actions[k, ..., 0], batch.rewards[k])
