"""What each script's `main` wires together: which network acts on which step, which networks each update
receives (online or target), which one is evaluated and which one is saved. The unit tests pin what the
algorithm's functions compute when handed the right arguments; these pin that `main` hands them the right ones.
Each test spies on the module's functions during a short run and compares what they received, by identity,
with the objects the run returns."""

import inspect
import os

import pytest
import torch

from conftest import SCRIPTS, declared, load, small_args


class Spy:
    """Wraps module-level functions of a script; every call is recorded as (name, {parameter: argument}) and
    passed on unchanged. `main` looks its functions up in the module at each call, so it calls the wrappers."""

    def __init__(self, module, names, monkeypatch):
        self.calls = []
        for name in names:
            fn = getattr(module, name)
            signature = inspect.signature(fn)

            def wrapper(*args, _fn=fn, _name=name, _signature=signature, **kwargs):
                self.calls.append((_name, dict(_signature.bind(*args, **kwargs).arguments)))
                return _fn(*args, **kwargs)

            monkeypatch.setattr(module, name, wrapper)

    def of(self, name) -> list:
        return [arguments for called, arguments in self.calls if called == name]


# {script: {function: {parameter: the key under which main returns the object it must be}}}; a list of keys for a
# parameter that takes a list of networks. Every listed function must be called, and every call must match.
# A script without an entry is held to its base's (a fork of TD3 to TD3's) until it declares its own here.
WIRING = {
    "td3": {
        "noisy_action": {"actor": "actor"},
        "update_critic": {"qf": "qf", "q_optimizer": "q_optimizer", "target_actor": "target_actor", "qf_target": "qf_target"},
        "update_actor": {"actor": "actor", "actor_optimizer": "actor_optimizer", "qf": "qf"},
        "soft_update": {"targets": ["target_actor", "qf_target"], "sources": ["actor", "qf"]},
        "evaluate": {"actor": "actor"},
    },
    "oparl": {
        "noisy_action": {"actor": "pessimistic_actor"},
        "optimistic_action": {"optimistic_actor": "optimistic_actor", "qf": "qf"},
        "update_critic": {
            "qf": "qf",
            "q_optimizer": "q_optimizer",
            "target_actor": "target_pessimistic_actor",
            "qf_target": "qf_target",
        },
        "update_actors": {
            "pessimistic_actor": "pessimistic_actor",
            "optimistic_actor": "optimistic_actor",
            "pessimistic_optimizer": "pessimistic_optimizer",
            "optimistic_optimizer": "optimistic_optimizer",
            "qf": "qf",
        },
        "soft_update": {"targets": ["target_pessimistic_actor", "qf_target"], "sources": ["pessimistic_actor", "qf"]},
        "evaluate": {"actor": "pessimistic_actor"},
    },
    # SAC and REDQ have no target actor: the target's next actions come from the online actor
    **{
        script: {
            "noisy_action": {"actor": "actor"},
            "update_critic": {"qf": "qf", "q_optimizer": "q_optimizer", "actor": "actor", "qf_target": "qf_target"},
            "update_actor": {"actor": "actor", "actor_optimizer": "actor_optimizer", "qf": "qf"},
            "update_alpha": {"actor": "actor", "a_optimizer": "a_optimizer"},
            "soft_update": {"targets": ["qf_target"], "sources": ["qf"]},
            "evaluate": {"actor": "actor"},
        }
        for script in ("sac", "redq")
    },
    "ppo": {
        "update_policy": {"rollout": "rollout", "agent": "agent", "optimizer": "optimizer"},
        "evaluate": {"agent": "agent", "normalizer": "normalizer"},
    },
    "rnd": {
        "update_policy": {"rollout": "rollout", "agent": "agent", "rnd_model": "rnd_model", "optimizer": "optimizer"},
        "evaluate": {"agent": "agent", "normalizer": "normalizer"},
    },
    "ebd": {
        "disagreement": {"forward_models": "forward_models"},
        "update_policy": {
            "rollout": "rollout",
            "agent": "agent",
            "forward_models": "forward_models",
            "optimizer": "optimizer",
        },
        "evaluate": {"agent": "agent", "normalizer": "normalizer"},
    },
}
# the key of the network that acts in evaluation and is saved as "actor" in the --save-model file
EVALUATED = {"oparl": "pessimistic_actor", "ppo": "agent"}  # RND and EBD inherit PPO's


def spied_run(script, tmp_path, monkeypatch, **overrides):
    monkeypatch.chdir(tmp_path)
    module = load(script)
    spy = Spy(module, declared(WIRING, script), monkeypatch)
    defaults = dict(env_id="Pendulum-v1", total_timesteps=600, learning_starts=300, batch_size=32, eval_frequency=300)
    result = module.main(small_args(module, **{**defaults, "save_model": True, "run_name": "wired", **overrides}))
    return spy, result


@pytest.fixture(scope="module")
def spied(tmp_path_factory):
    """One spied run per script, shared by the tests that read it (each script's tests share an xdist group)."""
    cache = {}

    def get(script):
        if script not in cache:
            cwd = tmp_path_factory.mktemp(script)
            with pytest.MonkeyPatch.context() as monkeypatch:
                spy, result = spied_run(script, cwd, monkeypatch)
            cache[script] = spy, {**result, "run_dir": os.path.join(cwd, result["run_dir"])}
        return cache[script]

    return get


SPIED = [pytest.param(s, marks=pytest.mark.xdist_group(f"wiring-{s}"), id=s) for s in SCRIPTS]


def test_every_script_has_its_wiring_pinned():
    missing = [s for s in SCRIPTS if declared(WIRING, s) is None]
    assert not missing, f"declare what main wires together for {missing} in WIRING, tests/test_wiring.py"
    assert set(WIRING) <= set(SCRIPTS), "WIRING names a script that does not exist"


@pytest.mark.parametrize("script", SPIED)
def test_main_hands_each_function_the_networks_it_must(script, spied):
    spy, result = spied(script)
    for function, expected in declared(WIRING, script).items():
        calls = spy.of(function)
        assert calls, f"main never called {function}"
        for arguments in calls:
            for parameter, key in expected.items():
                got = arguments[parameter]
                keys, got = (key, list(got)) if isinstance(key, list) else ([key], [got])
                if len(got) != len(keys) or any(g is not result[k] for g, k in zip(got, keys)):
                    names = [[name for name, value in result.items() if value is g] or "another object" for g in got]
                    pytest.fail(f"{function}({parameter}=...) got {names}, not {key}")


@pytest.mark.parametrize("script", SPIED)
def test_the_evaluated_actor_is_the_saved_actor(script, spied):
    spy, result = spied(script)
    evaluated = result[declared(EVALUATED, script) or "actor"]
    assert [step for step, _ in result["eval_returns"]] == [0, 300, 600]
    parameter = "actor" if "actor" in spy.of("evaluate")[0] else "agent"
    assert len(spy.of("evaluate")) == 3 and all(call[parameter] is evaluated for call in spy.of("evaluate"))
    saved = torch.load(os.path.join(result["run_dir"], f"{script}_continuous_action.cleanrl_model"), weights_only=True)
    assert saved["actor"].keys() == evaluated.state_dict().keys()
    for name, tensor in evaluated.state_dict().items():
        assert torch.equal(saved["actor"][name], tensor), name
    if "optimistic_actor" in saved:
        for name, tensor in result["optimistic_actor"].state_dict().items():
            assert torch.equal(saved["optimistic_actor"][name], tensor), name
        assert any(not torch.equal(saved["actor"][n], t) for n, t in result["optimistic_actor"].state_dict().items())


@pytest.mark.parametrize("ratio", [0.5, 0.3])
def test_oparl_acts_with_the_optimistic_actor_on_exactly_its_steps(ratio, tmp_path, monkeypatch):
    """After the random phase, step t is acted by the optimistic actor (max-std candidate) when
    is_optimistic_step(t) and by the noisy pessimistic actor otherwise, in that order."""
    spy, _ = spied_run("oparl", tmp_path, monkeypatch, optimistic_ratio=ratio)
    acted = [name for name, _ in spy.calls if name in ("noisy_action", "optimistic_action")]
    oparl = load("oparl")
    expected = ["optimistic_action" if oparl.is_optimistic_step(t, ratio) else "noisy_action" for t in range(300, 600)]
    assert acted == expected
    if ratio == 0.5:  # the release's alternation: pessimistic on even steps
        assert expected[:4] == ["noisy_action", "optimistic_action", "noisy_action", "optimistic_action"]


@pytest.mark.parametrize("script", [s for s in SPIED if "update_alpha" in declared(WIRING, s.values[0])])
def test_alpha_is_one_tensor_that_the_alpha_update_moves(script, spied):
    spy, result = spied(script)
    alphas = {id(call["alpha"]) for name in ("update_critic", "update_actor") for call in spy.of(name)}
    assert len(alphas) == 1, "the critic and actor updates read one alpha tensor, updated in place"
    log_alpha = result["a_optimizer"].param_groups[0]["params"][0]
    assert all(call["log_alpha"] is log_alpha for call in spy.of("update_alpha"))
    alpha = spy.of("update_actor")[-1]["alpha"]
    assert alpha.item() == pytest.approx(log_alpha.exp().item()) and result["alpha"] is alpha
    assert alpha.item() != 1.0  # it moved from its start
