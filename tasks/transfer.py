"""Model-based transfer to a new instance (DESIGN §4): the per-trial protocol.

For one test instance, one trial and one method:

1. The agent (Sarsa(λ), Fourier basis, fresh weights) starts from
   ``initial_planning_episodes`` simulated episodes on the method's model: the
   prior-mean model for the HiP-MDP, the average model, or the true simulator.
2. Then, for each of ``n_episodes`` real episodes: act and learn on the real
   instance; filter the HiP-MDP weight belief with every transition of the episode
   (one batched update after the episode: the belief is not used within it, so
   this is online filtering up to round-off, see ``_filter_episode``); then run
   ``planning_episodes`` simulated episodes on the model with the posterior-mean
   weights (the average and true models stay as they are); not after the last
   real episode, whose value function nothing would use. After the first real
   episode, ``first_planning_episodes`` simulated episodes instead, if set (not
   the paper's protocol: a check of whether the agent can use an instance
   identified in one episode, given more planning). With ``replan_after_first``
   (not the paper's protocol either), that planning starts from a fresh value
   function.

A method added with ``--method`` (``tasks.methods``) runs as a fourth: the agent
plans on its predictor adapted to the trial's real transitions so far, before the
first real episode (none) and after each one, as the HiP-MDP plans on its belief
filtered on them. An added policy instead acts with its own agent on the same real
episodes (same instance, same initial states), and plans as it likes.

Simulated episodes start from initial states of real episodes (the instance's own
start distribution): the planning start states are the first states of every real
episode so far plus ``n_start_states`` states drawn from the task's reset.

Methods are compared on the same instances and seeds: the environment's seed (so
every real episode's initial state), the planning start states and the agent's
random stream's seed depend only on (setting, trial), never on the method. The one
agent stream serves planning (start picks, exploration in simulated episodes) and
acting alike, and each method's planning draws from it differently, so the
exploration in real episodes is not paired across methods after the first
planning; the instance and the initial states are. An added policy's agent gets
a stream of its own, from the run's seed and the method's name
(``tasks.methods.method_seed``), so its exploration is not paired with the
others' at all; its instance and initial states are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from hipmdp.data import Transitions
from hipmdp.planning import LearnedModel, plan
from hipmdp.sarsa import init_state
from tasks.agents import Domain, SimulatorModel, episode_transitions, run_episode
from tasks.experiment import check_integer, check_positive

Array = np.ndarray

METHODS = ("true", "average", "hipmdp")
#: Their names in reports, tables and legends.
LABELS = {"true": "true model", "average": "average model", "hipmdp": "HiP-MDP"}


#: The most real episodes per trial a TransferConfig takes (the paper's text
#: implies at least 15; its figure is not in its source).
MAX_EPISODES = 10_000


@dataclass(frozen=True)
class TransferConfig:
    """Sizes of the protocol.

    Attributes:
        n_episodes: real episodes per trial.
        planning_episodes: simulated episodes after each real episode but the
            last (paper: 5).
        first_planning_episodes: simulated episodes after the first real episode
            instead of ``planning_episodes``; None (the paper's protocol) for the
            same number as after every other.
        initial_planning_episodes: simulated episodes before the first real one.
        replan_after_first: if True (not the paper's protocol), the value function
            is reset to its initial value after the first real episode, so the
            planning after it (``first_planning_episodes`` episodes, or
            ``planning_episodes``) starts from scratch on the model as updated by
            that episode: what the first planning on the prior model and the first
            real episode taught the agent is discarded.
        n_start_states: reset states added to the planning start states.
        max_steps: step limit of a real episode.
        planning_max_steps: step limit of a simulated episode.
    """

    n_episodes: int = 10
    planning_episodes: int = 5
    initial_planning_episodes: int = 30
    n_start_states: int = 20
    max_steps: int = 500
    planning_max_steps: int = 500
    first_planning_episodes: int | None = None
    replan_after_first: bool = False

    def __post_init__(self) -> None:
        check_positive(
            self, ("n_episodes", "n_start_states", "max_steps", "planning_max_steps")
        )
        if self.n_episodes > MAX_EPISODES:  # failed allocating, after the fit
            raise ValueError(
                f"n_episodes: expected at most {MAX_EPISODES:,} real episodes per "
                f"trial, got {self.n_episodes:,}"
            )
        for name in (
            "planning_episodes",
            "initial_planning_episodes",
            "first_planning_episodes",
        ):
            value = getattr(self, name)  # first_planning_episodes may be None
            if value is not None:
                check_integer(name, value, 0)
        if not isinstance(self.replan_after_first, bool):
            raise ValueError(
                f"replan_after_first: expected True or False, "
                f"got {self.replan_after_first!r}"
            )


class TrialJob(NamedTuple):
    """One unit of work: ``method`` on test setting ``setting`` (params), ``trial``;
    ``seed`` is the (setting, trial) seed sequence as a value, ``(entropy,
    spawn_key)``: every method's jobs share it (the added ones' too), and
    ``SeedSequence.spawn`` mutates the object it is called on, so sharing the
    object itself would give each method different streams when trials run
    in-process."""

    method: str
    setting: int
    trial: int
    params: Any
    seed: tuple[int, tuple[int, ...]]
    record: bool


def trial_label(job: TrialJob) -> str:
    """A trial as a progress bar names it: ``"hipmdp, setting 3, trial 0"``
    (settings and trials counted from 0)."""
    return f"{job.method}, setting {job.setting}, trial {job.trial}"


class EpisodeTrace(NamedTuple):
    """What the recording shows of one real episode (``T`` steps, ``K`` weights).

    states: ``s_0..s_T``, shape (T + 1, D). predicted: the model's one-step
    prediction of ``s_{t+1}`` from ``s_t`` with the model as it stood at step ``t``,
    shape (T, D) (None for a policy, which has no model). belief_mean,
    belief_std: the weight belief after ``t`` transitions, shape (T + 1, K)
    (HiP-MDP only, else None).
    """

    states: Array
    predicted: Array | None
    belief_mean: Array | None
    belief_std: Array | None


class TrialResult(NamedTuple):
    """Returns and steps per real episode, shape (E,); the belief mean after each
    episode, shape (E + 1, K) (HiP-MDP only); traces of recorded trials."""

    method: str
    setting: int
    trial: int
    returns: Array
    steps: Array
    weight_means: Array | None
    traces: list[EpisodeTrace] | None


# The fitted models, set once per worker process (see `set_models`): shipping them
# with every job would copy them once per trial.
_MODELS: dict[str, Any] = {}


def set_models(
    domain: Domain,
    config: TransferConfig,
    hipmdp_model,
    average_model,
    planning_wrapper: Callable[[Any, Any], Any] | None = None,
    added: Sequence[Any] = (),
):
    """Install what every trial needs in this process (a pool initializer).

    ``planning_wrapper(model, params)``, if given, turns the learned models (the
    HiP-MDP's and the average model's, not the true simulator) into the dynamics
    model the agent plans on, for the instance ``params``: e.g. a physical
    constraint applied to their predictions (and to added methods' predictors).
    Filtering and recording still see the learned model's own predictions.
    ``added``: fitted methods added with ``--method`` (``tasks.methods.Added``),
    run as methods of their own names, each trial on a fresh copy."""
    _MODELS.update(
        domain=domain,
        config=config,
        hipmdp=hipmdp_model,
        average=average_model,
        planning_wrapper=planning_wrapper,
        added={a.name: a for a in added},
    )


def _planning_model(model, job: TrialJob):
    wrapper = _MODELS.get("planning_wrapper")
    return (
        model if wrapper is None or job.method == "true" else wrapper(model, job.params)
    )


def _belief_moments(belief) -> tuple[Array, Array]:
    return np.asarray(belief.mean), np.sqrt(np.diag(np.asarray(belief.cov)))


def run_trial(job: TrialJob) -> TrialResult:
    """Run the protocol of the module docstring for one job."""
    domain: Domain = _MODELS["domain"]
    config: TransferConfig = _MODELS["config"]
    hip = _MODELS["hipmdp"]
    added = _MODELS.get("added", {}).get(job.method)
    if job.method not in METHODS and added is None:
        known = (*METHODS, *_MODELS.get("added", {}))
        raise ValueError(f"method: expected one of {known}, got {job.method!r}")
    if added is not None:
        # a fresh copy per trial: what adapt may keep on the object cannot carry
        # over to the next trial, whichever process runs it
        added = added._replace(method=added.fresh_copy())
    entropy, spawn_key = job.seed
    env_seed, start_seed, agent_seed = np.random.SeedSequence(
        entropy, spawn_key=spawn_key
    ).spawn(3)
    rng = np.random.default_rng(agent_seed)
    env = domain.make_env(
        job.params, seed=np.random.default_rng(env_seed), max_steps=config.max_steps
    )
    if added is not None and added.is_policy:
        return _policy_trial(job, added, env, domain, config)
    start_env = domain.make_env(job.params, seed=np.random.default_rng(start_seed))
    starts = [
        start_env.reset().observation["state"] for _ in range(config.n_start_states)
    ]
    task = domain.planning_task(job.params, config.planning_max_steps)
    basis, sarsa = domain.basis(), domain.sarsa

    belief = hip.prior() if job.method == "hipmdp" else None
    seen: list[Transitions] = []  # this trial's transitions, for an added method

    def model_now():
        if job.method == "true":
            return SimulatorModel(domain, job.params)
        if job.method == "average":
            return LearnedModel(_MODELS["average"], None, domain.angle_dims)
        if added is not None:  # adapted to every transition so far, as filtered
            data = _trial_data(seen, domain, env.control_timestep())
            key = (3, job.setting, job.trial, len(seen))
            try:
                predictor = added.adapt(data, key)
            except Exception as err:  # the user's adapt: say where, as planning does
                err.add_note(
                    f"(adapting method {added.name}, added with --method, to "
                    f"{len(data)} transitions after {len(seen)} real episodes; "
                    f"setting {job.setting}, trial {job.trial})"
                )
                raise
            return LearnedModel(predictor, None, domain.angle_dims)
        return LearnedModel(hip, belief, domain.angle_dims)

    def fresh_state():
        return init_state(domain.n_actions, basis.n_features, domain.initial_value)

    def plan_on(model, state, n_episodes: int):
        try:
            return plan(
                state, basis, sarsa, _planning_model(model, job), task,
                np.array(starts), n_episodes, rng=rng,
            ).state  # fmt: skip
        except Exception as err:
            if added is not None:  # the user's predictor: say whose
                err.add_note(
                    f"(planning on method {added.name}, added with --method; "
                    f"setting {job.setting}, trial {job.trial})"
                )
            raise

    model = model_now()
    state = plan_on(model, fresh_state(), config.initial_planning_episodes)

    returns, steps, weight_means, traces = [], [], [], []
    if belief is not None:
        weight_means.append(_belief_moments(belief)[0])
    for episode_index in range(config.n_episodes):
        episode = run_episode(env, basis, sarsa, state, rng=rng)
        state = episode.state
        returns.append(float(episode.rewards.sum()))
        steps.append(int(episode.actions.shape[0]))
        starts.append(episode.states[0])
        data = episode_transitions(
            episode, episode_index, domain.angle_dims, env.control_timestep()
        )
        seen.append(data)
        belief, trace = _filter_episode(model, hip, belief, data, episode, job)
        if trace is not None:
            traces.append(trace)
        if belief is not None:
            weight_means.append(_belief_moments(belief)[0])
        if episode_index == config.n_episodes - 1:
            break  # no episode follows to use another planning's value function
        model = model_now()
        if episode_index == 0 and config.replan_after_first:
            state = fresh_state()
        state = plan_on(model, state, _planning_episodes(config, episode_index))
    return TrialResult(
        job.method,
        job.setting,
        job.trial,
        np.array(returns),
        np.array(steps),
        np.array(weight_means) if weight_means else None,
        traces if job.record else None,
    )


def _policy_trial(job: TrialJob, added, env, domain: Domain, config) -> TrialResult:
    """A policy's trial (``tasks.methods``): a fresh agent acts and learns on
    the instance's ``config.n_episodes`` real episodes, which start from the
    states every method's do (``env``'s seed)."""
    returns, steps, traces = [], [], []
    try:
        agent = added.agent((4, job.setting, job.trial))
        for _ in range(config.n_episodes):
            states, rewards = _policy_episode(env, agent, added, domain.n_actions)
            returns.append(float(np.sum(rewards)))
            steps.append(len(rewards))
            if job.record:
                traces.append(EpisodeTrace(np.array(states), None, None, None))
    except Exception as err:
        err.add_note(f"(setting {job.setting}, trial {job.trial})")
        raise
    return TrialResult(
        job.method, job.setting, job.trial, np.array(returns), np.array(steps),
        None, traces if job.record else None,
    )  # fmt: skip


def _policy_episode(env, agent, added, n_actions: int) -> tuple[list, list]:
    """One real episode of a policy's agent: the states ``s_0..s_T`` and the
    ``T`` rewards."""
    time_step = env.reset()
    s = time_step.observation["state"].copy()
    states, rewards = [s], []
    while not time_step.last():
        a = added.act(agent, s, n_actions)
        time_step = env.step(a)
        s2, r = time_step.observation["state"].copy(), float(time_step.reward)
        terminal = time_step.last() and time_step.discount == 0.0
        added.observe(agent, s, a, r, s2, terminal)
        states.append(s2)
        rewards.append(r)
        s = s2
    added.end_episode(agent)
    return states, rewards


def _trial_data(parts: list[Transitions], domain: Domain, dt: float) -> Transitions:
    """A trial's real transitions so far, one instance (id 0); none at first."""
    if not parts:
        empty = np.empty((0, len(domain.low)))
        return Transitions(
            empty, np.empty(0, np.int64), empty, np.empty(0, np.int64),
            rewards=np.empty(0), dones=np.empty(0, bool),
            angle_dims=domain.angle_dims, dt=dt,
        )  # fmt: skip
    data = Transitions.concatenate(parts)
    return dataclasses.replace(data, instances=np.zeros(len(data), np.int64))


def _planning_episodes(config: TransferConfig, episode_index: int) -> int:
    """Simulated episodes after real episode ``episode_index`` (0-based)."""
    if episode_index == 0 and config.first_planning_episodes is not None:
        return config.first_planning_episodes
    return config.planning_episodes


def _filter_episode(model, hip, belief, data: Transitions, episode, job: TrialJob):
    """Filter the belief with an episode's transitions; trace it if recording.

    The belief the trial goes on with is always one batched update. Recorded
    trials also filter transition by transition, for the recording alone, so that
    it shows the belief and the one-step predictions at every step. The two agree
    only up to round-off (see tests/test_filter.py), and the swing-up agent
    amplifies round-off: when the recorded trial went on with the step-by-step
    belief, its HiP-MDP returns changed with ``--no-record`` (the paper run's
    setting 0, trial 0: episodes 2–5 of −84, −270, −59, −194 with the recording,
    −54, −60, −55, −66 without).

    Returns the belief after the episode and an :class:`EpisodeTrace` (or None).
    """
    after = hip.update(belief, data) if belief is not None else None
    if not job.record:
        return after, None
    predicted = np.empty_like(data.next_states)
    means, stds = [], []
    if belief is not None:
        m, s = _belief_moments(belief)
        means.append(m)
        stds.append(s)
    for t in range(len(data)):  # copies: a model may write over its inputs
        predicted[t] = model.predict(
            data.states[t : t + 1].copy(), data.actions[t : t + 1].copy()
        )
        if belief is not None:
            belief = hip.update(belief, data.take([t]))
            model = LearnedModel(hip, belief, model.angle_dims)
            m, s = _belief_moments(belief)
            means.append(m)
            stds.append(s)
    trace = EpisodeTrace(
        states=episode.states,
        predicted=predicted,
        belief_mean=np.array(means) if means else None,
        belief_std=np.array(stds) if stds else None,
    )
    return after, trace
