"""What each script's `main` wires together, and with which settings: which network acts on which step and with which
exploration noise, which networks and values each loss and update receives (online or target networks, the run's
flags, SAC's and REDQ's alpha and entropy target, PPO's discount and GAE lambda), what each step trains (the delayed
actor updates of --policy-frequency, SAC's target updates, REDQ's G critic updates), what changes between steps
(OPARL's reset and nothing else), which network is evaluated and which one is saved. The unit tests pin what the
algorithm's functions compute when handed the right arguments; these pin that `main` hands them the right ones.

Each test spies on the module's functions during a short run and compares what they received with the objects the
run returns (by identity) and with the run's flags (by value). `main` calls its functions through rl_utils.per_seed,
which looks each name up in the module when it is called, so it calls the spies; for one seed, per_seed hands a
function seed 0's share of each tensor with a seeds dimension (a view of it: SAC's alpha, log_alpha) and the
networks themselves. The spy also stands in for the module's `Run`, to learn the run's networks and optimizers and
where each step ends."""

import copy
import dataclasses
import inspect
import os

import numpy as np
import pytest
import torch

from conftest import SCRIPTS, declared, load, small_args
from rl_utils import make_env


class Spy:
    """Wraps module-level functions of a script; every call is recorded as (name, {parameter: argument}) and passed
    on unchanged, what it returned recorded under "return". Each step's end is recorded as ("end_step", {"step": s}).
    `hooks` {name: fn(spy, arguments)} run before a spied function, and {"end_step": fn(spy, step)} at a step's end."""

    def __init__(self, module, names, monkeypatch, hooks=None):
        self.calls, self.nets, self.optimizers, hooks = [], {}, {}, hooks or {}
        for name in names:
            fn = getattr(module, name)
            signature = inspect.signature(fn)

            def wrapper(*args, _fn=fn, _name=name, _signature=signature, **kwargs):
                arguments = dict(_signature.bind(*args, **kwargs).arguments)
                self.calls.append((_name, arguments))
                if _name in hooks:
                    hooks[_name](self, arguments)
                arguments["return"] = _fn(*args, **kwargs)  # "return" cannot be a parameter's name
                return arguments["return"]

            monkeypatch.setattr(module, name, wrapper)
        spy = self

        class RecordingRun(module.Run):
            def start(self, envs, device, nets, optimizers, **parts):
                spy.nets, spy.optimizers = nets, optimizers
                return super().start(envs, device, nets, optimizers, **parts)

            def end_step(self, step, *args, **kwargs):
                spy.calls.append(("end_step", {"step": step}))
                if "end_step" in hooks:
                    hooks["end_step"](spy, step)
                return super().end_step(step, *args, **kwargs)

        monkeypatch.setattr(module, "Run", RecordingRun)

    @staticmethod
    def label(name, arguments) -> str:
        """A call's name; `optimize` calls by the loss they step on: optimize(qf_loss)."""
        return f"optimize({arguments['name']})" if name == "optimize" else name

    def of(self, label) -> list:
        return [arguments for name, arguments in self.calls if self.label(name, arguments) == label]

    def steps(self) -> list:
        """[(step, [labels of the calls in that step])], then ("end", [the calls after the last step])."""
        steps, current, step = [], [], 0
        for name, arguments in self.calls:
            if name == "end_step":
                assert arguments["step"] == step, f"step {arguments['step']} ended where step {step} was due"
                steps.append((step, current))
                current, step = [], step + 1
            else:
                current.append(self.label(name, arguments))
        return steps + [("end", current)]


# {script: {function: {parameter: what main must hand it}}}, where what main must hand is
#   "key" or "key.attribute": the object main returns under that key (its attribute), by identity; for a tensor
#       that carries the seeds dimension, seed 0's share of it (a view of it) passes
#   "args" or "args.flag": the run's Args (or one flag's value), by value
#   a list of those: a parameter that takes a list of networks
# `optimize(loss, name, *optimizers)` is listed by the loss's name: "optimize(qf_loss)". A list of such dicts: the
# calls cycle through them (RND's extrinsic, then intrinsic GAE). Every listed function must be called, and every call
# must match. A script without an entry is held to its base's (a fork of TD3 to TD3's) until it declares its own here.
WIRING = {
    "td3": {
        "noisy_action": {"actor": "actor", "exploration_noise": "args.exploration_noise"},
        "critic_loss": {"qf": "qf", "target_actor": "target_actor", "qf_target": "qf_target", "args": "args"},
        "optimize(qf_loss)": {"optimizers": ["q_optimizer"]},
        "policy_loss": {"actor": "actor", "qf": "qf"},
        "optimize(actor_loss)": {"optimizers": ["actor_optimizer"]},
        "soft_update": {"targets": ["target_actor", "qf_target"], "sources": ["actor", "qf"], "tau": "args.tau"},
        "evaluate": {"num_episodes": "args.eval_episodes"},
    },
    "oparl": {
        "noisy_action": {"actor": "actor", "exploration_noise": "args.exploration_noise"},
        "optimistic_action": {"optimistic_actor": "optimistic_actor", "qf": "qf", "args": "args"},
        "critic_loss": {"qf": "qf", "target_actor": "target_actor", "qf_target": "qf_target", "args": "args"},
        "optimize(qf_loss)": {"optimizers": ["q_optimizer"]},
        "policy_losses": {"actor": "actor", "optimistic_actor": "optimistic_actor", "qf": "qf"},
        "optimize(actor_loss)": {"optimizers": ["actor_optimizer", "optimistic_optimizer"]},
        "soft_update": {
            "targets": ["target_actor", "qf_target"],
            "sources": ["actor", "qf"],
            "tau": "args.tau",
        },
        "evaluate": {"num_episodes": "args.eval_episodes"},
    },
    # SAC and REDQ have no target actor: the target's next actions come from the online actor
    **{
        script: {
            "noisy_action": {"actor": "actor"},
            "critic_loss": {"qf": "qf", "actor": "actor", "qf_target": "qf_target", "alpha": "alpha", "args": "args"},
            "optimize(qf_loss)": {"optimizers": ["q_optimizer"]},
            "policy_loss": {"actor": "actor", "qf": "qf", "alpha": "alpha"},
            "optimize(actor_loss)": {"optimizers": ["actor_optimizer"]},
            "alpha_loss_fn": {"actor": "actor", "log_alpha": "log_alpha"},
            "optimize(alpha_loss)": {"optimizers": ["a_optimizer"]},
            "soft_update": {"targets": ["qf_target"], "sources": ["qf"], "tau": "args.tau"},
            "evaluate": {"num_episodes": "args.eval_episodes"},
        }
        for script in ("sac", "redq")
    },
    "ppo": {
        "compute_gae": {
            "rewards": "rollout.rewards",
            "values": "rollout.values",
            "episode_ends": "rollout.episode_ends",
            "gamma": "args.gamma",
            "gae_lambda": "args.gae_lambda",
        },
        "update_policy": {"rollout": "rollout", "agent": "agent", "optimizer": "optimizer", "args": "args"},
        "evaluate": {"num_episodes": "args.eval_episodes"},
    },
    # the exploration methods: an extrinsic GAE as PPO's, then an intrinsic one on the intrinsic value head
    **{
        script: {
            **({"disagreement": {"forward_models": "forward_models"}} if script == "ebd" else {}),
            "advantages_and_returns": {"rollout": "rollout", "args": "args"},
            "compute_gae": [
                {
                    "rewards": "rollout.rewards",
                    "values": "rollout.values",
                    "episode_ends": "rollout.episode_ends",
                    "gamma": "args.gamma",
                    "gae_lambda": "args.gae_lambda",
                },
                {"values": "rollout.int_values", "gamma": "args.int_gamma", "gae_lambda": "args.gae_lambda"},
            ],
            "update_policy": {
                "rollout": "rollout",
                "agent": "agent",
                model: model,
                "optimizer": "optimizer",
                "args": "args",
            },
            "evaluate": {"num_episodes": "args.eval_episodes"},
        }
        for script, model in (("rnd", "rnd_model"), ("ebd", "forward_models"))
    },
}


def td3_step(module, args, step) -> list:
    labels = ["noisy_action", "critic_loss", "optimize(qf_loss)"]
    if step % args.policy_frequency == 0:  # the delayed actor update, and the targets with it
        labels += ["policy_loss", "optimize(actor_loss)", "soft_update"]
    return labels


def oparl_step(module, args, step) -> list:
    act = "optimistic_action" if module.is_optimistic_step(step, args.optimistic_ratio) else "noisy_action"
    labels = [act, "critic_loss", "optimize(qf_loss)"]
    if step % args.policy_frequency == 0:  # both actors in one delayed update, and the targets
        labels += ["policy_losses", "optimize(actor_loss)", "soft_update"]
    return labels


def sac_step(module, args, step) -> list:
    labels = ["noisy_action", "critic_loss", "optimize(qf_loss)"]
    if step % args.policy_frequency == 0:  # --policy-frequency actor (and alpha) updates every --policy-frequency steps
        labels += ["policy_loss", "optimize(actor_loss)", "alpha_loss_fn", "optimize(alpha_loss)"] * args.policy_frequency
    if step % args.target_network_frequency == 0:
        labels += ["soft_update"]
    return labels


def redq_step(module, args, step) -> list:
    labels = ["noisy_action"] + ["critic_loss", "optimize(qf_loss)", "soft_update"] * args.utd_ratio  # G updates
    return labels + ["policy_loss", "optimize(actor_loss)", "alpha_loss_fn", "optimize(alpha_loss)"]  # then one actor


def rollout_step(update: list):
    """An on-policy script's step: `update` where a rollout is full (not a last partial one), nothing otherwise."""

    def step_labels(module, args, step) -> list:
        full = step % args.num_steps == args.num_steps - 1 and step < args.total_timesteps // args.num_steps * args.num_steps
        return update if full else []

    return step_labels


# {script: labels(module, args, step) of the spied calls a training step makes (after learning starts, for the
# off-policy scripts; before it they make none)}. Each step begins with an evaluation where one is due.
SCHEDULE = {
    "td3": td3_step,
    "oparl": oparl_step,
    "sac": sac_step,
    "redq": redq_step,
    "ppo": rollout_step(["compute_gae", "update_policy"]),
    "rnd": rollout_step(["advantages_and_returns", "compute_gae", "compute_gae", "update_policy"]),
    "ebd": rollout_step(["disagreement", "advantages_and_returns", "compute_gae", "compute_gae", "update_policy"]),
}
# the network evaluated (and saved as "actor" in the --save-model file), where it is not "actor"
EVALUATED = {"ppo": "agent"}  # RND and EBD inherit PPO's
# (source, copy) of a reset every --reset-frequency training iterations (OPARL: pi_opt <- pi_pes)
RESETS = {"oparl": ("actor", "optimistic_actor")}
# the entropy target alpha is tuned to, on Hopper-v4 (3 action dimensions): SAC's -|A|; REDQ's release's table
ENTROPY_TARGET = {"sac": -3.0, "redq": -1.0}
# the arguments of the policy update that come from the advantage computation's result, in its order
ADVANTAGES = {
    "ppo": ("compute_gae", ["advantages", "returns"]),
    **{script: ("advantages_and_returns", ["advantages", "returns", "int_returns"]) for script in ("rnd", "ebd")},
}

# the spied run's flags: each differs from the default and from the other flags a function could be handed by mistake
# (--exploration-noise from --policy-noise 0.2, --gamma from --int-gamma and --gae-lambda, --policy-frequency from
# --target-network-frequency), and an OPARL reset falls within the run
SETTINGS = {
    "exploration_noise": 0.15,
    "tau": 0.01,
    "gamma": 0.97,
    "policy_frequency": 3,
    "target_network_frequency": 2,
    "gae_lambda": 0.9,
    "int_gamma": 0.98,
    "reset_frequency": 40,
}
RUN = {"env_id": "Hopper-v4", "total_timesteps": 600, "learning_starts": 300, "batch_size": 32, "eval_frequency": 300}


def run_settings(module, **overrides) -> dict:
    """SETTINGS and `overrides`, less the flags the script does not have (RUN's are small_args' to sort)."""
    fields = {f.name for f in dataclasses.fields(module.Args)}
    return {k: v for k, v in {**SETTINGS, **overrides}.items() if k in fields or k in RUN}


def network_state(spy) -> dict:
    """Every parameter and buffer of the run's networks and every optimizer's state, copied, by name."""
    state = {f"{name}.{key}": t.detach().clone() for name, net in spy.nets.items() for key, t in net.state_dict().items()}
    for name, optimizer in spy.optimizers.items():
        for i, param_state in optimizer.state_dict()["state"].items():
            state.update({f"{name}.state.{i}.{key}": t.clone() for key, t in param_state.items()})
    return state


class BetweenSteps:
    """What changes in the networks and optimizers between the end of a training step and the next step's first
    update (its critic loss), where the loop evaluates, acts and steps the env, and OPARL resets its optimistic actor:
    {step: (the names of the entries that changed, the state after)}."""

    def __init__(self, learning_starts: int):
        self.learning_starts, self.before, self.changes = learning_starts, None, {}

    def end_step(self, spy, step):
        self.step = step + 1
        self.before = network_state(spy) if self.step >= self.learning_starts else None

    def critic_loss(self, spy, arguments):
        if self.before is not None:  # the step's first update
            after = network_state(spy)
            changed = {k for k in {*self.before, *after} if k not in self.before or k not in after}
            changed |= {k for k in self.before.keys() & after.keys() if not torch.equal(self.before[k], after[k])}
            self.changes[self.step] = changed, after if changed else None
            self.before = None


def spied_run(script, tmp_path, monkeypatch, **overrides):
    """A short run of `script` on Hopper-v4 with SETTINGS, spied on: (spy, what main returned, its Args)."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    names = {label.split("(")[0] for label in declared(WIRING, script)}
    watch = BetweenSteps(overrides.get("learning_starts", RUN["learning_starts"]))
    hooks = {"end_step": watch.end_step, "critic_loss": watch.critic_loss} if "critic_loss" in names else {}
    spy = Spy(module, names, monkeypatch, hooks)
    spy.between_steps = watch
    args = small_args(module, **{**RUN, "save_model": True, "run_name": "wired", **run_settings(module, **overrides)})
    result = module.main(args)
    if "a_optimizer" in result:
        result["log_alpha"] = result["a_optimizer"].param_groups[0]["params"][0]
    return spy, {**result, "run_dir": os.path.join(tmp_path, result["run_dir"])}, args


@pytest.fixture(scope="module")
def spied(tmp_path_factory):
    """One spied run per script, shared by the tests that read it (each script's tests share an xdist group)."""
    cache = {}

    def get(script):
        if script not in cache:
            with pytest.MonkeyPatch.context() as monkeypatch:
                cache[script] = spied_run(script, tmp_path_factory.mktemp(script), monkeypatch)
        return cache[script]

    return get


SPIED = [pytest.param(s, marks=pytest.mark.xdist_group(f"wiring-{s}"), id=s) for s in SCRIPTS]


def expected_of(path: str, result: dict, args):
    head, *attributes = path.split(".")
    value = args if head == "args" else result[head]
    for attribute in attributes:
        value = getattr(value, attribute)
    return value


def is_handed(got, expected) -> bool:
    """`got` is `expected`, or seed 0's share of it (per_seed's view of a tensor with a seeds dimension)."""
    return got is expected or (isinstance(got, torch.Tensor) and got._base is expected)


def equal_states(a, b) -> bool:
    """Two state_dicts (nested dicts and lists of tensors and numbers) hold the same values."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and torch.equal(a, b)
    if isinstance(a, (dict, list, tuple)):
        pairs = zip(a.values(), b.values()) if isinstance(a, dict) else zip(a, b)
        return type(a) is type(b) and len(a) == len(b) and all(equal_states(x, y) for x, y in pairs)
    return a == b


def check_argument(function, parameter, got, path, result, args):
    paths, gots = (path, list(got)) if isinstance(path, list) else ([path], [got])
    if all(p.split(".")[0] == "args" for p in paths):  # values: the run's flags
        expected = [expected_of(p, result, args) for p in paths]
        assert gots == expected, f"{function}({parameter}={gots}), not {path} = {expected}"
        return
    if len(gots) != len(paths) or not all(is_handed(g, expected_of(p, result, args)) for g, p in zip(gots, paths)):
        names = [[name for name, value in result.items() if is_handed(g, value)] or "another object" for g in gots]
        pytest.fail(f"{function}({parameter}=...) got {names}, not {path}")


def test_every_script_has_its_wiring_pinned():
    missing = [s for s in SCRIPTS if declared(WIRING, s) is None or declared(SCHEDULE, s) is None]
    assert not missing, f"declare what main wires together for {missing} in WIRING and SCHEDULE, tests/test_wiring.py"
    assert set(WIRING) <= set(SCRIPTS), "WIRING names a script that does not exist"


@pytest.mark.parametrize("script", SPIED)
def test_main_hands_each_function_the_networks_and_settings_it_must(script, spied):
    spy, result, args = spied(script)
    for function, expected in declared(WIRING, script).items():
        calls = spy.of(function)
        assert calls, f"main never called {function}"
        specs = expected if isinstance(expected, list) else [expected]
        for i, arguments in enumerate(calls):
            for parameter, path in specs[i % len(specs)].items():
                check_argument(function, parameter, arguments[parameter], path, result, args)


@pytest.mark.parametrize("script", SPIED)
def test_each_step_trains_as_its_schedule_says(script, spied):
    """Step by step, the spied calls in order: an evaluation where one is due, nothing else before learning starts,
    then what SCHEDULE says (TD3 and OPARL update their actors only on steps divisible by --policy-frequency, SAC
    makes --policy-frequency actor updates on those steps, REDQ G critic updates a step, PPO learns once a rollout)."""
    spy, _, args = spied(script)
    module, schedule = load(script), declared(SCHEDULE, script)
    starts = getattr(args, "learning_starts", 0)
    expected = [
        (step, ["evaluate"] * (step % args.eval_frequency == 0) + (schedule(module, args, step) if step >= starts else []))
        for step in range(args.total_timesteps)
    ] + [("end", ["evaluate"])]
    got = spy.steps()
    for (step, calls), (_, expected_calls) in zip(got, expected):
        assert calls == expected_calls, f"step {step} made {calls}, not {expected_calls}"
    assert len(got) == len(expected)


@pytest.mark.parametrize("script", [s for s in SPIED if "critic_loss" in declared(WIRING, s.values[0])])
def test_between_steps_nothing_changes_but_a_due_reset(script, spied):
    """From the end of a training step to the next step's first update, no network and no optimizer state changes,
    except at OPARL's reset: on every --reset-frequency-th training iteration the optimistic actor becomes a copy of
    the pessimistic one, and nothing else changes (not its optimizer, not the critics)."""
    spy, result, args = spied(script)
    changes = spy.between_steps.changes
    assert sorted(changes) == list(range(args.learning_starts, args.total_timesteps))  # every training step watched
    reset = declared(RESETS, script)
    resets = []
    for step, (changed, after) in changes.items():
        iteration = step - args.learning_starts + 1
        if not (reset and args.reset_frequency and iteration % args.reset_frequency == 0):
            assert not changed, f"{sorted(changed)} changed before step {step}'s update"
            continue
        source, copy = reset
        keys = list(result[copy].state_dict())
        assert changed and changed <= {f"{copy}.{key}" for key in keys}, f"the reset at step {step} changed {changed}"
        for key in keys:
            assert torch.equal(after[f"{copy}.{key}"], after[f"{source}.{key}"]), f"step {step}: {copy}.{key}"
        resets.append(step)
    if reset:
        assert len(resets) == (args.total_timesteps - args.learning_starts) // args.reset_frequency > 0


@pytest.mark.parametrize("script", SPIED)
def test_the_evaluated_actor_is_the_saved_actor(script, spied):
    """Every evaluation runs one policy, and it acts as the evaluated network (OPARL's pessimistic actor, the
    on-policy agent's mean on the training statistics, which it leaves as they are); --save-model saves that network."""
    spy, result, args = spied(script)
    evaluated = result[declared(EVALUATED, script) or "actor"]
    assert [step for step, _ in result["eval_returns"]] == [0, 300, 600]
    calls = spy.of("evaluate")
    policy = calls[0]["policy"]
    assert len(calls) == 3 and all(call["policy"] is policy for call in calls)
    env = make_env(args.env_id, 0)
    obs = np.random.default_rng(0).normal(size=(1, *env.observation_space.shape)).astype(np.float32)
    normalizer = result.get("normalizer")
    with torch.no_grad():
        if normalizer is not None:  # the on-policy scripts: the mean action on the observation statistics, clipped
            statistics = copy.deepcopy(normalizer.state_dict())
            x = torch.as_tensor(normalizer.observation(obs, update=False))
            expected = evaluated.actor_mean(x).numpy().clip(env.action_space.low, env.action_space.high)
        else:  # the deterministic actor (SAC's and REDQ's mean action), on each seed's observation: one here
            expected = getattr(evaluated, "deterministic_action", evaluated)(torch.as_tensor(obs[0]))[None].numpy()
    np.testing.assert_array_equal(policy(obs), expected)
    if normalizer is not None:
        assert equal_states(normalizer.state_dict(), statistics), "evaluating moved the observation statistics"
    saved = torch.load(os.path.join(result["run_dir"], f"{script}_continuous_action.cleanrl_model"), weights_only=True)
    assert saved["actor"].keys() == evaluated.state_dict().keys()
    for name, tensor in evaluated.state_dict().items():
        assert torch.equal(saved["actor"][name], tensor), name
    if "optimistic_actor" in saved:
        for name, tensor in result["optimistic_actor"].state_dict().items():
            assert torch.equal(saved["optimistic_actor"][name], tensor), name
        assert any(not torch.equal(saved["actor"][n], t) for n, t in result["optimistic_actor"].state_dict().items())


@pytest.mark.parametrize("script", [s for s in SPIED if declared(ADVANTAGES, s.values[0])])
def test_the_policy_update_learns_from_the_advantages_just_computed(script, spied):
    spy, _, _ = spied(script)
    source, parameters = declared(ADVANTAGES, script)
    latest, updates = None, 0
    for name, arguments in spy.calls:
        if name == source:
            latest = arguments["return"]
        elif name == "update_policy":
            assert latest is not None and all(arguments[p] is r for p, r in zip(parameters, latest)), parameters
            latest, updates = None, updates + 1  # each rollout's own
    assert updates == 2


@pytest.mark.parametrize("ratio", [pytest.param(0.5, marks=pytest.mark.xdist_group("wiring-oparl")), 0.3])
def test_oparl_acts_with_the_optimistic_actor_on_exactly_its_steps(ratio, spied, tmp_path, monkeypatch):
    """After the random phase, step t is acted by the optimistic actor (max-std candidate) when
    is_optimistic_step(t) and by the noisy pessimistic actor otherwise, in that order."""
    if ratio == 0.5:  # the default: the shared run's
        spy, _, _ = spied("oparl")
    else:
        spy, _, _ = spied_run("oparl", tmp_path, monkeypatch, optimistic_ratio=ratio)
    acted = [name for name, _ in spy.calls if name in ("noisy_action", "optimistic_action")]
    oparl = load("oparl")
    expected = ["optimistic_action" if oparl.is_optimistic_step(t, ratio) else "noisy_action" for t in range(300, 600)]
    assert acted == expected
    if ratio == 0.5:  # the release's alternation: pessimistic on even steps
        assert expected[:4] == ["noisy_action", "optimistic_action", "noisy_action", "optimistic_action"]


ALPHA_SCRIPTS = [s for s in SPIED if "alpha_loss_fn" in declared(WIRING, s.values[0])]


@pytest.mark.parametrize("script", ALPHA_SCRIPTS)
def test_alpha_is_one_tensor_that_the_alpha_update_moves(script, spied):
    spy, result, _ = spied(script)
    alpha, log_alpha = result["alpha"], result["log_alpha"]
    assert all(is_handed(call["alpha"], alpha) for name in ("critic_loss", "policy_loss") for call in spy.of(name)), (
        "the critic and actor losses read one alpha tensor, updated in place"
    )
    assert all(is_handed(call["log_alpha"], log_alpha) for call in spy.of("alpha_loss_fn"))
    assert alpha.item() == pytest.approx(log_alpha.exp().item())
    assert alpha.item() != 1.0  # it moved from its start


@pytest.mark.parametrize("script", ALPHA_SCRIPTS)
def test_alpha_is_tuned_to_the_algorithms_entropy_target(script, spied):
    spy, _, _ = spied(script)
    assert {call["target_entropy"] for call in spy.of("alpha_loss_fn")} == {declared(ENTROPY_TARGET, script)}


def test_redq_tunes_alpha_to_the_target_entropy_given(tmp_path, monkeypatch):
    """--target-entropy overrides the release's table (Hopper-v4: -1)."""
    spy, _, _ = spied_run(
        "redq", tmp_path, monkeypatch, target_entropy=-2.5, total_timesteps=66, learning_starts=64, eval_frequency=66
    )
    assert {call["target_entropy"] for call in spy.of("alpha_loss_fn")} == {-2.5}


@pytest.mark.parametrize("script", [s for s in SCRIPTS if "QEnsemble" in dir(load(s))])
def test_an_actor_step_computes_no_gradient_for_the_critics(script, tmp_path, monkeypatch):
    """main freezes the critics (requires_grad off) for each actor step and unfreezes them for their own: an actor's
    loss computes no gradient for the critics' weights (work wasted, and recorded into every --cudagraphs replay)."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    seen = []

    def requires_grad(spy, arguments):
        seen.append((arguments["name"], {p.requires_grad for p in spy.nets["qf"].parameters()}))

    Spy(module, ["optimize"], monkeypatch, hooks={"optimize": requires_grad})
    module.main(small_args(module, env_id="Pendulum-v1", total_timesteps=260, learning_starts=250, batch_size=32))
    assert {name for name, _ in seen} >= {"qf_loss", "actor_loss"}
    assert all(flags == {False} for name, flags in seen if name == "actor_loss"), seen
    assert all(flags == {True} for name, flags in seen if name == "qf_loss"), seen
