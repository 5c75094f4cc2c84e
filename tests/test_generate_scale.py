"""Generation at scale: the open-loop `mujoco.rollout` path is the environment bit
for bit; a killed run resumes to the same bytes; corrupt shards are redone; the
bytes do not depend on the workers (process pool, Dask); another run's directory
is refused untouched."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shlex
import shutil
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest

from hipmdp import Transitions, shards
from tasks import acrobot, cartpole, collect, generate, rollout
from tasks._common import wrap_scalar_angle

CARTPOLES = [cartpole.CartpoleParams(), cartpole.CartpoleParams(0.5, 0.3, 0.8)]
ACROBOTS = [acrobot.AcrobotParams(), acrobot.AcrobotParams(1.3, 0.7, 0.9, 1.1)]
RUN = [
    "--domain", "cartpole", "--policy", "open-loop", "--instances", "6",
    "--shard-size", "2", "--episodes-per-instance", "3", "--seed", "11",
    "--no-progress",
]  # fmt: skip


def files(directory):
    """Every file of a run directory by name, with its bytes."""
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def copy_unfinished(reference, run, edit=lambda manifest: None):
    """A copy of the finished run ``reference`` at ``run``, its manifest edited
    in place by ``edit`` and marked unfinished, and shard 1 gone (the shard a
    resume has to redo)."""
    shutil.copytree(reference, run)
    manifest = json.loads((run / "manifest.json").read_text())
    edit(manifest)
    manifest["complete"] = False
    (run / "manifest.json").write_text(json.dumps(manifest))
    (run / "shard-00001.npz").unlink()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("reference")
    generate.main([*RUN, "--out", str(out)])
    return out


#: a nominal acrobot (20 steps of 10 ms per action) and a light, short-linked one
#: (80 steps of 2.5 ms, tasks.acrobot.sub_steps): open-loop rolls them out apart
MIXED_STEPS = [acrobot.AcrobotParams(), acrobot.AcrobotParams(0.6, 0.4, 1.0, 0.5)]


@pytest.mark.parametrize(
    "domain, instances",
    [("acrobot", ACROBOTS), ("cartpole", CARTPOLES), ("acrobot", MIXED_STEPS)],
)
def test_open_loop_equals_stepping_the_environment(domain, instances):
    """`collect_open_loop` on instance `i` is the environment seeded with the
    first stream of `rng.spawn(B)[i]` stepped with the actions of the second:
    same states, actions, rewards and episode ends, exactly."""
    spec, e_per, steps = collect.get_domain(domain), 3, 120
    got = rollout.collect_open_loop(
        domain,
        instances,
        episodes_per_instance=e_per,
        rng=np.random.default_rng(9),
        instance_ids=[4, 7],
        max_steps=steps,
        chunk=7,  # episodes end inside and across chunks
    )
    rows = {k: [] for k in ("states", "actions", "next_states", "rewards", "dones")}
    for params, stream in zip(
        instances, np.random.default_rng(9).spawn(2), strict=True
    ):
        init_rng, action_rng = stream.spawn(2)
        env = spec.make_env(params, seed=init_rng, max_steps=steps)
        actions = action_rng.integers(spec.n_actions, size=(e_per, steps))
        for episode in range(e_per):
            step = env.reset()
            for a in actions[episode]:
                s = step.observation["state"]
                step = env.step(int(a))
                for key, value in zip(
                    rows,
                    (s, a, step.observation["state"], step.reward, step.last()),
                    strict=True,
                ):
                    rows[key].append(value)
                if step.last():
                    break
    t = got.transitions
    for key, values in rows.items():
        np.testing.assert_array_equal(getattr(t, key), np.array(values), err_msg=key)
    assert got.n_episodes == 6 and not got.diverged
    np.testing.assert_array_equal(np.unique(t.instances), [4, 7])
    for b, params in zip([4, 7], instances, strict=True):  # each id's own row
        assert got.parameters.row(b) == dataclasses.asdict(params)
    if domain == "cartpole":  # random forces topple the pole: early ends are tested
        assert np.count_nonzero(t.dones) == 6 and len(t) < 6 * steps


@pytest.mark.parametrize("chunk", [1, 300])
def test_open_loop_from_fast_states_reaches_the_goal_and_wraps_as_the_environment(
    chunk,
):
    """Acrobot episodes from fast, far-flung starts: most end at the goal,
    angles wrap past ±π, and the others run to the step limit; one step per
    `mujoco.rollout` call and the whole episode in one. Each episode equals the
    environment set to the same start and stepped with the same actions."""
    rng = np.random.default_rng(12)
    n, steps = 8, 300
    s0 = np.c_[rng.uniform(-np.pi, np.pi, (n, 2)), rng.uniform(-6, 6, (n, 2))]
    s0[-1] = 0.0  # hanging still: random torques do not swing it up in time
    instance = np.arange(n) % 2
    actions = rng.integers(3, size=(n, steps))
    got = rollout.rollout_episodes(
        "acrobot", ACROBOTS, instance, s0, actions, chunk=chunk
    )
    assert not (got.diverged >= 0).any()
    lengths, wrapped = [], False
    for e in range(n):
        env = acrobot.swingup(ACROBOTS[instance[e]], seed=0, max_steps=steps)
        env.reset()
        with env.physics.reset_context():
            env.physics.data.qpos[:] = s0[e, :2]
            env.physics.data.qvel[:] = s0[e, 2:]
        states = [env.task.get_observation(env.physics)["state"]]
        rewards = []
        for a in actions[e]:
            step = env.step(int(a))
            states.append(step.observation["state"])
            rewards.append(step.reward)
            wrapped |= bool(
                np.abs(np.diff(np.array(states)[-2:, :2], axis=0)).max() > 4
            )
            if step.last():
                break
        k = len(rewards)
        lengths.append(k)
        assert got.lengths[e] == k, e
        np.testing.assert_array_equal(got.states[e, : k + 1], np.array(states))
        np.testing.assert_array_equal(got.rewards[e, :k], rewards)
    assert min(lengths) < steps // 2 and max(lengths) == steps  # goals and a limit
    assert wrapped  # an angle crossed ±π


def test_open_loop_drops_a_diverging_episode():
    """A velocity of 1e150 makes MuJoCo reset the data (time goes back): the
    episode is reported as diverged at its first step, its neighbours are not."""
    s0 = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1e150, 0.0], [0.1, 0, 0, 0]])
    result = rollout.rollout_episodes(
        "acrobot", ACROBOTS, np.array([0, 0, 1]), s0, np.ones((3, 10), int), chunk=4
    )
    np.testing.assert_array_equal(result.diverged, [-1, 0, -1])
    assert np.isfinite(result.states[[0, 2]]).all()


def test_wrap_matches_the_environment_scalar_wrap():
    x = np.array([-7.0, -np.pi, np.pi, 3 * np.pi, 1e6, -1e-300, 2 * np.pi, 5.5])
    expected = [wrap_scalar_angle(v) for v in x]
    np.testing.assert_array_equal(rollout.wrap(x), expected)


# A generation process that SIGKILLs itself right after writing its third shard
# file, before the progress log records it: a hard kill at a chosen point, not
# raced.
_KILL_AFTER_THIRD_SHARD = """
import os, signal, sys
from tasks import generate
write, written = generate.shards.write_shard, []
def write_then_die(*args, **kwargs):
    digest = write(*args, **kwargs)
    written.append(digest)
    if len(written) == 3:
        os.kill(os.getpid(), signal.SIGKILL)
    return digest
generate.shards.write_shard = write_then_die
generate.main(sys.argv[1:])
"""


def test_killed_run_resumes_to_the_bytes_of_an_uninterrupted_run(tmp_path):
    argv = [
        "--domain", "acrobot", "--instances", "24", "--shard-size", "1",
        "--episodes-per-instance", "1", "--max-steps", "200", "--no-progress",
    ]  # fmt: skip
    killed = tmp_path / "killed"
    run = subprocess.run(
        [sys.executable, "-c", _KILL_AFTER_THIRD_SHARD, *argv, "--out", str(killed)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        timeout=300,  # a guard against hanging, not a timing check
    )
    assert run.returncode == -signal.SIGKILL
    # the manifest as written at the start (nothing finished); the two finished
    # shards in the progress log; the third's file on disk but recorded nowhere
    written = json.loads((killed / "manifest.json").read_text())
    assert not any(e["sha256"] for e in written["shards"])
    manifest = shards.read_manifest(killed)
    finished = [e["index"] for e in manifest["shards"] if e["sha256"]]
    assert not manifest["complete"] and len(finished) == 2
    assert sorted(shards.read_progress(killed)) == sorted(finished)
    assert len(list(killed.glob("shard-*.npz"))) == 3
    resumed = generate.main([*argv, "--out", str(killed), "--resume"])
    assert set(resumed.redone) == set(range(24)) - set(finished)
    generate.main([*argv, "--out", str(tmp_path / "whole")])
    assert files(killed) == files(tmp_path / "whole")  # and no progress log left


# A generation process sent SIGTERM (as a batch system stops a job) halfway
# through writing its second shard file: at a chosen point, not raced.
_TERMINATE_WHILE_WRITING_SECOND_SHARD = """
import os, signal, sys
from tasks import generate
atomic_write, files = generate.shards.atomic_write, []
def write_and_terminate(path, write):
    if path.name.startswith("shard-"):
        files.append(path.name)
    if len(files) != 2 or path.name != files[1]:
        return atomic_write(path, write)
    print(path.name, flush=True)  # the shard being written when SIGTERM comes
    def halves(fh):
        data = bytearray()
        write(type("Sink", (), {"write": lambda self, b: data.extend(b)})())
        fh.write(data[: len(data) // 2])
        os.kill(os.getpid(), signal.SIGTERM)
        fh.write(data[len(data) // 2 :])
    return atomic_write(path, halves)
generate.shards.atomic_write = write_and_terminate
generate.main(sys.argv[1:])
"""


@pytest.mark.parametrize("workers", ["1", "2"])
def test_sigterm_keeps_the_finished_shards_and_says_how_to_resume(tmp_path, workers):
    """SIGTERM ended a run with status 143 and no word (a batch system's stop
    looked like a crash). It stops the run as Ctrl-C does, with one line naming
    the shards kept and the command that resumes; a shard being written when
    it came is written whole and kept first, no temporary file is left, and the
    resumed run has the bytes of an uninterrupted one."""
    argv = [
        "--domain", "acrobot", "--instances", "6", "--shard-size", "1",
        "--episodes-per-instance", "1", "--max-steps", "20", "--no-progress",
    ]  # fmt: skip
    out = tmp_path / "terminated"
    script = _TERMINATE_WHILE_WRITING_SECOND_SHARD
    run = subprocess.run(
        [sys.executable, "-c", script, *argv, "--workers", workers, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,  # a guard against hanging, not a timing check
    )
    assert run.returncode == 143, run.stderr
    # kept: the shard being written, the one before, and any other finished by
    # then (the pool's workers run on)
    kept = [e for e in shards.read_manifest(out)["shards"] if e["sha256"]]
    assert run.stdout.strip() in {e["file"] for e in kept} and len(kept) >= 2
    command = ["python", "-m", "tasks.generate", *argv, "--workers", workers]
    resume = shlex.join([*command, "--out", str(out), "--resume"])
    assert run.stderr == (
        f"python -m tasks.generate: terminated: {len(kept)} of 6 shards finished "
        f"are kept in {out}; resume with the same command plus --resume: {resume}\n"
    )
    assert shards.atomic_temporaries(out, "*") == []
    resumed = generate.main([*argv, "--out", str(out), "--resume"])
    assert len(resumed.redone) == 6 - len(kept)
    generate.main([*argv, "--out", str(tmp_path / "whole")])
    assert files(out) == files(tmp_path / "whole")


def test_corrupt_truncated_and_missing_shards_are_detected_and_redone(
    reference, tmp_path
):
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    whole = (run / "shard-00000.npz").read_bytes()
    (run / "shard-00000.npz").write_bytes(whole[: len(whole) // 2])  # truncated
    flipped = bytearray((run / "shard-00001.npz").read_bytes())
    flipped[-100] ^= 1  # one bit of the last array's data
    (run / "shard-00001.npz").write_bytes(bytes(flipped))
    (run / "shard-00002.npz").unlink()
    dataset = shards.Dataset(run)
    with pytest.raises(ValueError, match="does not match its checksum"):
        dataset.load(instances=[2])
    with pytest.raises(ValueError, match=f"{run}: shard shard-00002.npz is missing"):
        dataset.load(instances=[4])
    resumed = generate.main([*RUN, "--out", str(run), "--resume"])
    assert resumed.redone == (0, 1, 2)
    assert files(run) == files(reference)
    again = generate.main([*RUN, "--out", str(run), "--resume"])
    assert again.redone == ()


def test_process_pool_gives_the_same_bytes(reference, tmp_path):
    generate.main([*RUN, "--out", str(tmp_path), "--workers", "2"])
    assert files(tmp_path) == files(reference)


def test_dask_cluster_gives_the_same_bytes(reference, tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.Client(
        processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None
    ) as client:
        generate.main(
            [*RUN, "--out", str(tmp_path), "--scheduler", client.scheduler.address]
        )
    assert files(tmp_path) == files(reference)


def test_the_command_on_a_tcp_cluster_gives_the_same_bytes(reference, tmp_path):
    """`python -m tasks.generate --scheduler` sends its functions to the workers
    named by module (`tasks.generate.run_shard`), not pickled by value from
    `__main__`: a worker runs its own code, the code its software check is about
    (by value, the check could not find `local_software` on the worker, and a
    worker ran the client's `run_shard` with its own other modules). The
    workers are this process's threads; the client is the command."""
    distributed = pytest.importorskip("distributed")
    with distributed.Client(
        processes=False, n_workers=1, threads_per_worker=1, protocol="tcp",
        host="127.0.0.1", dashboard_address=None,
    ) as client:  # fmt: skip
        run = subprocess.run(
            [sys.executable, "-m", "tasks.generate", *RUN, "--out", str(tmp_path),
             "--scheduler", client.scheduler.address],
            capture_output=True,
            text=True,
            timeout=300,  # a guard against hanging, not a timing check
        )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert files(tmp_path) == files(reference)


def test_a_scheduler_that_does_not_answer_stops_the_run_before_any_file(
    tmp_path, capsys
):
    pytest.importorskip("distributed")
    import dask

    out = tmp_path / "run"
    with socket.socket() as taken:  # a port bound but not listening: refused
        taken.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{taken.getsockname()[1]}"
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
            with pytest.raises(SystemExit) as stopped:
                generate.main([*RUN, "--out", str(out), "--scheduler", address])
    assert stopped.value.code == 1
    err = capsys.readouterr().err
    assert address in err
    # said before Dask's retries end (they are its own: a scheduler may be
    # starting), and before its error
    waiting = (
        f"--scheduler {address}: no answer yet; waiting up to 1 s "
        "(distributed.comm.timeouts.connect)\n"
    )
    assert err.startswith(waiting) and err.count(address) == 2
    # Dask's own error: its retries ran out; nothing accepted the connection
    assert "after 1 s" in err and "accepted the connection" not in err
    assert not out.exists()


def test_a_server_that_accepts_but_never_answers_stops_the_run_before_any_file(
    tmp_path, capsys
):
    """An address that accepts the connection and stays silent (another server,
    the dashboard's port) made the run wait for ever: Dask reads the handshake
    without a deadline, `Client(timeout=...)` too. It gets Dask's connect
    timeout now, and the one line of an unreachable scheduler."""
    pytest.importorskip("distributed")
    import threading

    import dask

    stop, accepted = threading.Event(), []

    def silent(server):
        with server:
            for _ in range(600):  # a guard of a minute, not a timing check:
                if stop.is_set():  # without the deadline, Dask then reads a
                    break  # close, and the test fails instead of hanging
                with contextlib.suppress(OSError):
                    accepted.append(server.accept()[0])
        for connection in accepted:
            connection.close()

    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.1)
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    out = tmp_path / "run"
    thread = threading.Thread(target=silent, args=(server,), daemon=True)
    thread.start()
    try:
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
            with pytest.raises(SystemExit) as stopped:
                generate.main([*RUN, "--out", str(out), "--scheduler", address])
    finally:
        stop.set()
        thread.join()
    assert accepted  # it was reached, and stayed silent
    assert stopped.value.code == 1
    assert capsys.readouterr().err == (
        f"--scheduler {address}: no answer yet; waiting up to 1 s "
        "(distributed.comm.timeouts.connect)\n"
        f"python -m tasks.generate: error: Timed out trying to connect to {address} "
        "after 1 s (it accepted the connection but did not answer as a Dask "
        "scheduler)\n"
    )
    assert not out.exists()


def test_shards_without_a_manifest_are_refused_untouched(reference, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    (run / "manifest.json").unlink()
    before = files(run)
    with pytest.raises(SystemExit):
        generate.main([*RUN, "--out", str(run)])
    assert "holds shard files but no manifest" in capsys.readouterr().err
    assert files(run) == before


def test_a_progress_log_without_a_manifest_is_refused_untouched(tmp_path, capsys):
    """A folder's own progress.jsonl (a training log, say) was deleted by a run
    started there."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "progress.jsonl").write_text('{"epoch": 1}\n')
    (run / "notes.txt").write_text("mine")
    before = files(run)
    with pytest.raises(SystemExit):
        generate.main([*RUN, "--out", str(run)])
    assert "holds a progress.jsonl that no run" in capsys.readouterr().err
    assert files(run) == before


@pytest.mark.parametrize(
    "extra, unfinished, message",
    [
        (["--seed", "12"], False, "holds a different run (seed: 11 -> 12)"),
        (["--policy", "random", "--resume"], False, "policy: 'open-loop' -> 'random'"),
        # which shards, and why: a finished run's shard was lost
        (
            [],
            True,
            "holds this run, unfinished (1 of 3 shards to do; damaged (missing, "
            "or not matching its checksum): shard-00001.npz); pass --resume to "
            "continue it",
        ),
        # every option that changes the data is part of the run
        (["--episodes-per-instance", "2"], False, "episodes_per_instance: 3 -> 2"),
        (["--max-steps", "50", "--resume"], False, "max_steps: None -> 50"),
        (["--shard-size", "3", "--resume"], False, "shard_size: 2 -> 3"),
        # resuming: the options the run was made with, not only another --out
        (
            ["--instances", "4", "--shard-size", "3", "--resume"],
            False,
            "holds a different run (instances: 6 -> 4; shard_size: 2 -> 3); to "
            "resume it, pass the options it was made with (--instances 6 "
            "--shard-size 2), or choose another --out",
        ),
        (
            ["--max-steps", "50", "--book-inertia", "--domain", "acrobot", "--resume"],
            False,
            "pass the options it was made with (--domain cartpole; without "
            "--book-inertia --max-steps --vary)",
        ),
        # a distribution's differing keys alone, sorted, not two whole dicts
        (
            [
                "--distribution",
                "relative-normal",
                "--vary",
                "pole_mass=0.1:0.5",
                "--resume",
            ],
            False,
            "holds a different run (distribution.kind: 'uniform' -> "
            "'relative-normal'; distribution.sigma: None -> 0.1; "
            "distribution.vary.pole_half_length: [0.25, 1.0] -> None; "
            "distribution.vary.pole_mass: [0.05, 0.5] -> [0.1, 0.5]); to resume "
            "it, pass the options it was made with (--distribution uniform; "
            "without --sigma --vary)",
        ),
    ],
)
def test_another_or_unfinished_run_is_refused_untouched(
    reference, tmp_path, capsys, extra, unfinished, message
):
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    if unfinished:
        (run / "shard-00001.npz").unlink()
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in run.iterdir()}
    with pytest.raises(SystemExit) as stopped:
        generate.main([*RUN, *extra, "--out", str(run)])
    assert stopped.value.code == 2 and message in capsys.readouterr().err
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in run.iterdir()}
    assert after == before


def test_an_unfinished_run_names_as_damaged_only_the_shards_recorded_finished(
    reference, tmp_path, capsys
):
    """A killed run whose shard 0 was recorded finished and then damaged, and
    whose shards 1 and 2 never finished: all three are to do, but only shard 0
    is damaged (the others were never written, not lost)."""
    from tests.test_shards import unfinished_copy

    run = tmp_path / "run"
    whole = unfinished_copy(reference, run)
    shards.append_progress(run, whole["shards"][0])
    (run / "shard-00000.npz").write_bytes(b"damaged")
    for name in ("shard-00001.npz", "shard-00002.npz"):
        (run / name).unlink()
    before = files(run)
    with pytest.raises(SystemExit) as stopped:
        generate.main([*RUN, "--out", str(run)])
    assert stopped.value.code == 2
    assert (
        "holds this run, unfinished (3 of 3 shards to do; damaged (missing, or not "
        "matching its checksum): shard-00000.npz); pass --resume to continue it"
    ) in capsys.readouterr().err
    assert files(run) == before


def test_resume_advice_keeps_seed_0_and_says_the_vary_order_matters(tmp_path, capsys):
    """A run made with --seed 0 is advised --seed 0 (0 is not an absent
    option); its two --vary, whose order the draws follow and the manifest
    does not keep, come with that caveat, as does the refusal of the same
    ranges given in another order."""
    run = tmp_path / "run"
    base = [
        "--domain", "cartpole", "--policy", "open-loop", "--instances", "2",
        "--episodes-per-instance", "1", "--no-progress", "--out", str(run),
    ]  # fmt: skip
    vary = ["--vary", "pole_mass=0.1:0.2", "--vary", "cart_mass=0.5:1.5"]
    generate.main([*base, *vary, "--seed", "0"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        generate.main([*base, "--seed", "3", "--resume"])
    assert (
        "pass the options it was made with (--seed 0 --vary cart_mass=0.5:1.5 "
        "--vary pole_mass=0.1:0.2 (in the order they were first given)), or"
    ) in capsys.readouterr().err
    with pytest.raises(SystemExit):
        generate.main([*base, *vary[2:], *vary[:2], "--seed", "0", "--resume"])
    assert (
        "other instances (made by another version of the code or with the --vary "
        "in another order?)"
    ) in capsys.readouterr().err


def test_a_run_of_this_config_with_other_instances_is_refused_untouched(
    reference, tmp_path, capsys
):
    """Same config, other instance parameters (drawn by another version of the
    code): resuming would add shards of the new draws to those of the old."""

    def other_first_pole(manifest):
        manifest["shards"][0]["parameters"][0][1] += 0.01  # the first pole's mass

    run = tmp_path / "run"
    copy_unfinished(reference, run, other_first_pole)
    before = files(run)
    with pytest.raises(SystemExit) as stopped:
        generate.main([*RUN, "--out", str(run), "--resume"])
    assert stopped.value.code == 2
    assert "holds this configuration but other instances" in capsys.readouterr().err
    assert files(run) == before


def test_a_log_left_by_a_kill_after_the_final_manifest_is_cleared(reference, tmp_path):
    """Killed between writing the complete manifest and deleting the progress
    log: the next command finds the run finished and clears the log, so the
    folder holds what an uninterrupted run's does."""
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    for entry in shards.read_manifest(run)["shards"]:
        shards.append_progress(run, entry)
    again = generate.main([*RUN, "--out", str(run), "--resume"])
    assert again.redone == ()
    assert files(run) == files(reference)


def test_temporary_files_a_kill_left_are_removed_on_resume(reference, tmp_path):
    """A kill inside an atomic write leaves `.NAME.*.tmp` beside the manifest or
    a shard: the resumed run deletes them, so the folder ends as an
    uninterrupted run's."""
    run = tmp_path / "run"
    copy_unfinished(reference, run)
    (run / ".shard-00001.npz.k1ll3d.tmp").write_bytes(b"half a shard")
    (run / ".manifest.json.k1ll3d.tmp").write_text("{")
    assert generate.main([*RUN, "--out", str(run), "--resume"]).redone == (1,)
    assert files(run) == files(reference)


def test_a_stale_record_of_a_corrupt_shard_is_redone(reference, tmp_path):
    """A progress line for a shard whose file is later damaged (and a resume
    killed before it cleared the log): the checksum still finds it, and it is
    redone."""
    from tests.test_shards import unfinished_copy

    run = tmp_path / "run"
    whole = unfinished_copy(reference, run)
    shards.append_progress(run, whole["shards"][1])  # as the run recorded it
    (run / "shard-00001.npz").write_bytes(b"damaged")
    resumed = generate.main([*RUN, "--out", str(run), "--resume"])
    assert resumed.redone == (0, 1, 2)  # 0 and 2 unrecorded, 1 damaged
    assert files(run) == files(reference)


class Dies(generate.InlineExecutor):
    """An executor killed before it runs any shard."""

    def submit(self, fn, /, *args, **kwargs):
        raise RuntimeError("killed")


def test_a_stale_record_is_cleared_before_its_shard_is_redone(reference, tmp_path):
    """The resumed run takes the progress log into its manifest and deletes it
    before any shard: killed then, the log's stale line for the damaged shard
    must not make it look finished again."""
    from tests.test_shards import unfinished_copy

    run = tmp_path / "run"
    whole = unfinished_copy(reference, run)
    diverged = {"instance": 2, "episode": 1, "step": 4, "reason": "non-finite state"}
    counts = {"episodes": 3, "transitions": 12, "diverged_episodes": 1}
    shards.append_progress(  # a record of the shard with a diverged episode
        run, whole["shards"][1] | {"counts": counts, "diverged": [diverged]}
    )
    (run / "shard-00001.npz").write_bytes(b"damaged")
    config = generate.parse_config([*RUN, "--out", str(run), "--resume"])
    with pytest.raises(RuntimeError, match="killed"):
        generate.generate(config, executor=Dies())
    assert not (run / shards.PROGRESS).exists()
    entry = shards.read_manifest(run)["shards"][1]
    assert (entry["sha256"], entry["counts"], entry["diverged"]) == (None, None, [])


def test_a_finished_run_is_left_as_it_is(reference, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in run.iterdir()}
    for resume in ([], ["--resume"]):
        assert generate.main([*RUN, *resume, "--out", str(run)]).redone == ()
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in run.iterdir()}
    assert after == before


def test_a_finished_run_redoing_a_damaged_shard_is_unfinished_until_it_is_done(
    reference, tmp_path
):
    """Resuming a finished run whose shard was damaged, killed before the redo:
    the manifest must not say complete (it did, and readers trusted it)."""
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    (run / "shard-00001.npz").write_bytes(b"damaged")
    config = generate.parse_config([*RUN, "--out", str(run), "--resume"])
    with pytest.raises(RuntimeError, match="killed"):
        generate.generate(config, executor=Dies())
    manifest = shards.read_manifest(run)
    assert not manifest["complete"]
    assert manifest["shards"][1]["sha256"] is None
    assert not shards.Dataset(run).complete
    assert generate.main([*RUN, "--out", str(run), "--resume"]).redone == (1,)
    assert files(run) == files(reference)


@pytest.mark.parametrize("fast", [False, True])
def test_a_run_from_before_the_finer_steps_resumes_only_if_they_do_not_apply(
    tmp_path, fast, capsys
):
    """A manifest written before fast acrobots took finer steps names no
    ``sub_steps``: every instance then took 20. Resuming it is right for nominal
    instances, but would mix 10 ms shards with finer ones for fast instances."""
    vary = ["link_mass_2=0.2:0.25", "link_length_2=0.2:0.25"] if fast else []
    args = [
        "--domain", "acrobot", "--policy", "open-loop", "--instances", "2",
        "--shard-size", "1", "--episodes-per-instance", "1", "--max-steps", "5",
        "--seed", "3", "--no-progress", "--out", str(tmp_path),
        *[f"--vary={v}" for v in vary],
    ]  # fmt: skip
    generate.main(args)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    steps = {n for e in manifest["shards"] for n in e.pop("sub_steps")}
    assert steps == ({20 * 2**5} if fast else {20})
    manifest["complete"] = False
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    (tmp_path / "shard-00001.npz").write_bytes(b"damaged")
    if fast:
        with pytest.raises(SystemExit):
            generate.main([*args, "--resume"])
        assert "shard 0 was simulated with other steps per action" in (
            capsys.readouterr().err
        )
        assert (tmp_path / "shard-00001.npz").read_bytes() == b"damaged"
    else:
        assert generate.main([*args, "--resume"]).redone == (1,)
        # the manifest names the steps again, as a run of this version writes it
        manifest = json.loads((tmp_path / "manifest.json").read_text())
        assert [e["sub_steps"] for e in manifest["shards"]] == [[20], [20]]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"source_sha256": "0" * 64}, "(the source of hipmdp, tasks or the MJCF"),
        ({"packages": {"mujoco": "3.16.0"}}, "(numpy, mujoco changed since"),
        # a run from before the record seeded each shard, not each instance
        (None, "(it records none: made before 2026-12-04, when each shard's"),
    ],
)
def test_resume_refuses_a_run_made_by_other_software(
    reference, tmp_path, capsys, change, message
):
    """--resume compared only the config and the instances: shards made before
    a code edit or a package upgrade mixed with shards made after it."""

    def other_software(manifest):
        if change is None:
            del manifest["software"]
        else:
            packages = manifest["software"]["packages"]
            if "packages" in change:
                packages = packages | change["packages"] | {"numpy": "1.0"}
            manifest["software"] |= change | {"packages": packages}

    run = tmp_path / "run"
    copy_unfinished(reference, run, other_software)
    before = files(run)
    with pytest.raises(SystemExit):
        generate.main([*RUN, "--out", str(run), "--resume"])
    assert message in capsys.readouterr().err
    assert files(run) == before


def test_mixed_software_continues_and_records_which_shards_each_made(
    reference, tmp_path, capsys
):
    """The refusal had no way round: any source edit stranded a long run.
    --mixed-software continues it and the manifest says which shards the
    earlier software made (here twice: two earlier versions, shards redone by
    the last one leave their lists)."""
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    manifest = json.loads((run / "manifest.json").read_text())
    fresh = manifest["software"]
    first = fresh | {"source_sha256": "1" * 64}
    second = fresh | {"source_sha256": "2" * 64}
    manifest |= {"software": first, "complete": False}
    (run / "manifest.json").write_text(json.dumps(manifest))
    (run / "shard-00001.npz").unlink()
    with pytest.raises(SystemExit):
        generate.main([*RUN, "--out", str(run), "--mixed-software"])
    assert "(--mixed-software): needs --resume" in capsys.readouterr().err
    resume = [*RUN, "--out", str(run), "--resume", "--mixed-software"]
    assert generate.main(resume).redone == (1,)
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["earlier_software"] == [{"software": first, "shards": [0, 2]}]
    assert manifest["software"] == fresh and manifest["complete"]
    # the same code made every shard here, so the data equal the reference's
    assert {k: v for k, v in files(run).items() if k != "manifest.json"} == {
        k: v for k, v in files(reference).items() if k != "manifest.json"
    }
    manifest |= {"software": second, "complete": False}
    (run / "manifest.json").write_text(json.dumps(manifest))
    (run / "shard-00000.npz").unlink()
    assert generate.main(resume).redone == (0,)
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["earlier_software"] == [
        {"software": first, "shards": [2]},
        {"software": second, "shards": [1]},
    ]
    assert manifest["software"] == fresh
    # this version redoes the last shards the earlier ones made: none is left to
    # name, and the run is the reference's, manifest and all
    manifest["complete"] = False
    (run / "manifest.json").write_text(json.dumps(manifest))
    for k in (1, 2):
        (run / f"shard-0000{k}.npz").unlink()
    assert generate.main(resume).redone == (1, 2)
    assert files(run) == files(reference)


@pytest.mark.parametrize("policy", ["random", "sarsa", "open-loop"])
def test_an_instances_data_do_not_depend_on_the_shard_size(tmp_path, policy):
    """Shard k's episodes came from one stream (1, split, k): an instance's data
    changed with --shard-size and, under the random policy, with the lengths of
    the episodes of the instances before it in its shard."""
    argv = ["--domain", "acrobot", "--instances", "5", "--episodes-per-instance",
            "2", "--max-steps", "15", "--policy", policy, "--seed", "3",
            "--no-progress"]  # fmt: skip
    runs = {}
    for size in (1, 2, 5):
        out = tmp_path / f"size{size}"
        generate.main([*argv, "--shard-size", str(size), "--out", str(out)])
        runs[size] = Transitions.load(out, instances=range(5))
    for size in (2, 5):
        for name in ("states", "actions", "next_states", "instances", "rewards"):
            np.testing.assert_array_equal(
                getattr(runs[size], name), getattr(runs[1], name), err_msg=name
            )


def test_a_run_by_other_software_killed_before_any_shard_resumes_as_it_is(
    reference, tmp_path
):
    """No shard finished, so nothing would mix: it was refused all the same."""
    run = tmp_path / "run"
    run.mkdir()
    manifest = json.loads((reference / "manifest.json").read_text())
    manifest["software"]["source_sha256"] = "0" * 64
    manifest["complete"] = False
    (run / "manifest.json").write_text(json.dumps(manifest))
    assert generate.main([*RUN, "--out", str(run), "--resume"]).redone == (0, 1, 2)
    assert files(run) == files(reference)  # the manifest records this software


def test_a_finished_run_made_by_other_software_is_left_as_it_is(reference, tmp_path):
    """Nothing to do, so nothing mixes: the same command after an upgrade still
    finds the run finished."""
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    manifest = json.loads((run / "manifest.json").read_text())
    manifest["software"]["source_sha256"] = "0" * 64
    (run / "manifest.json").write_text(json.dumps(manifest))
    before = files(run)
    assert generate.main([*RUN, "--out", str(run)]).redone == ()
    assert files(run) == before


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(actions=np.ones(6, int)), r"actions must have shape \(E, T\)"),
        (dict(initial_states=np.zeros((2, 3))), r"initial_states must have shape"),
        (dict(episode_instance=np.array([0, 2])), r"of shape \(2,\) in \[0, 2\]"),
        (dict(episode_instance=np.array([-1, 0])), "2 integer indices into 2 inst"),
        # a bool array passed the bounds and selected by mask; a float one failed
        # as an index deep inside
        (dict(episode_instance=np.array([True, False])), "got bool of shape"),
        (dict(episode_instance=np.array([0.0, 1.0])), "got float64 of shape"),
        (dict(actions=np.full((2, 6), 3)), r"actions must be integer indices in \[0"),
        (dict(actions=np.full((2, 6), -1)), r"3\), got int64 of shape .* \[-1, -1\]"),
        (dict(actions=np.full((2, 6), 1.5)), r"in \[0, 3\), got float64"),
        (dict(chunk=0), "chunk must be a positive int"),
        (dict(actions=np.ones((2, 0), int)), r"actions must have shape \(E, T\)"),
        (
            dict(
                actions=np.ones((0, 6), int),
                initial_states=np.zeros((0, 4)),
                episode_instance=np.zeros(0, int),
            ),
            r"actions must have shape \(E, T\)",
        ),
    ],
)
def test_bad_open_loop_arguments_are_refused_naming_them(change, message):
    arguments = dict(
        episode_instance=np.array([0, 1]),
        initial_states=np.zeros((2, 4)),
        actions=np.ones((2, 6), int),
    )
    arguments.update(change)
    with pytest.raises(ValueError, match=message):
        rollout.rollout_episodes("acrobot", ACROBOTS, **arguments)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(instances=[]), "at least one parameter set"),
        (dict(instances=[ACROBOTS[0], CARTPOLES[0]]), "must be AcrobotParams"),
        (dict(instance_ids=[3, 3]), "instance_ids must be 2 distinct ints"),
        (dict(instance_ids=[3]), "instance_ids must be 2 distinct ints"),
        (dict(instance_ids=[3, 4, 5]), "instance_ids must be 2 distinct ints"),
        (dict(instance_ids=[0.5, 1.5]), "instance_ids must be 2 distinct ints"),
        (dict(episodes_per_instance=0), "episodes_per_instance must be a positive"),
        (dict(max_steps=0), "max_steps must be a positive int"),
        (dict(rng=[np.random.default_rng(0)]), "rng: expected .* a sequence of 2"),
    ],
)
def test_bad_open_loop_gathering_arguments_are_refused_naming_them(change, message):
    """As `tasks.collect.collect` refuses them, not as a failure further in."""
    arguments = dict(
        instances=ACROBOTS, episodes_per_instance=1, max_steps=3,
        rng=np.random.default_rng(0),
    )  # fmt: skip
    arguments.update(change)
    with pytest.raises(ValueError, match=message):
        rollout.collect_open_loop("acrobot", arguments.pop("instances"), **arguments)


def test_open_loop_counts_may_be_numpy_integers():
    """As `tasks.collect.collect` takes them (an np.int64 from an array of
    counts was refused as "not a positive int")."""
    result = rollout.collect_open_loop(
        "acrobot", ACROBOTS, episodes_per_instance=np.int64(1),
        rng=np.random.default_rng(0), max_steps=np.int64(3), chunk=np.int32(4),
    )  # fmt: skip
    assert result.n_episodes == 2 and len(result.transitions) == 2 * 3


def test_open_loop_episodes_run_to_the_tasks_own_step_limit_by_default():
    """With no max_steps, an episode that neither reaches the goal nor diverges
    ends at the limit the environment (and so `tasks.collect.collect`) uses."""
    result = rollout.collect_open_loop(
        "acrobot", ACROBOTS[:1], episodes_per_instance=2,
        rng=np.random.default_rng(0),
    )  # fmt: skip
    t = result.transitions
    limit = acrobot.swingup(seed=0).task.max_steps
    assert not result.diverged and not acrobot.goal_reached(t.next_states).any()
    np.testing.assert_array_equal(np.flatnonzero(t.dones), [limit - 1, 2 * limit - 1])


def test_a_non_finite_state_is_a_divergence_even_at_a_terminal_step(monkeypatch):
    """A state that is not finite, with no MuJoCo reset, ends its episode as
    diverged at that step; so does one that the task would also call terminal
    (the cart far out): the divergence comes first."""
    real = rollout.mj_rollout.rollout
    n_sub = cartpole.N_SUB_STEPS
    at = rollout.mujoco.mj_stateSize(
        cartpole.make_model(CARTPOLES[0]), rollout.mujoco.mjtState.mjSTATE_TIME
    )

    def poisoned(models, data, physics, control):
        state, sensors = real(models, data, physics, control)
        end_of_step_3 = 4 * n_sub - 1
        state[:, end_of_step_3, at + 3] = np.nan  # the pole's speed
        state[0, end_of_step_3, at] = 100.0  # episode 0: the cart has failed too
        return state, sensors

    monkeypatch.setattr(rollout.mj_rollout, "rollout", poisoned)
    result = rollout.rollout_episodes(
        "cartpole", CARTPOLES, np.array([0, 1]), np.zeros((2, 4)),
        np.ones((2, 6), int),
    )  # fmt: skip
    np.testing.assert_array_equal(result.diverged, [3, 3])


def test_a_divergence_in_a_later_chunk_is_counted_from_the_episodes_start(
    monkeypatch,
):
    """Three control steps per `mujoco.rollout` call: a state made NaN at the
    end of the second step of the second call is step 3 + 1 = 4 of the
    episode, not 1 of the chunk."""
    real = rollout.mj_rollout.rollout
    n_sub, calls = cartpole.N_SUB_STEPS, []
    at = rollout.mujoco.mj_stateSize(
        cartpole.make_model(CARTPOLES[0]), rollout.mujoco.mjtState.mjSTATE_TIME
    )

    def poisoned(models, data, physics, control):
        state, sensors = real(models, data, physics, control)
        calls.append(state.shape)
        if len(calls) == 2:
            state[:, 2 * n_sub - 1, at + 3] = np.nan  # the pole's speed
        return state, sensors

    monkeypatch.setattr(rollout.mj_rollout, "rollout", poisoned)
    result = rollout.rollout_episodes(
        "cartpole", CARTPOLES, np.array([0, 1]), np.zeros((2, 4)),
        np.ones((2, 6), int), chunk=3,
    )  # fmt: skip
    assert len(calls) == 2 and calls[1][1] == 3 * n_sub  # steps 3 to 5
    np.testing.assert_array_equal(result.diverged, [4, 4])


def test_open_loop_gathering_drops_a_diverged_episode_and_names_it(monkeypatch):
    """An episode that diverges (here instance 0's second, from a velocity of
    1e150) is reported with its instance id and its episode within the
    instance, and none of its steps is kept."""
    real = rollout.rollout_episodes

    def blown_up(domain, instances, episode_instance, initial_states, actions, **kw):
        initial_states = initial_states.copy()
        initial_states[1, 2] = 1e150
        return real(domain, instances, episode_instance, initial_states, actions, **kw)

    monkeypatch.setattr(rollout, "rollout_episodes", blown_up)
    result = rollout.collect_open_loop(
        "acrobot", ACROBOTS, episodes_per_instance=2, max_steps=10,
        rng=np.random.default_rng(0), instance_ids=[4, 9],
    )  # fmt: skip
    (divergence,) = result.diverged
    assert divergence[:3] == (4, 1, 0)
    t = result.transitions
    assert result.n_episodes == 4 and len(t) == 3 * 10
    assert np.isfinite(t.next_states).all() and np.abs(t.next_states).max() < 100
    np.testing.assert_array_equal(np.bincount(t.instances)[[4, 9]], [10, 20])


def test_a_folder_another_run_writes_to_is_refused(tmp_path, capsys):
    """Two runs into one --out at once both reported success, over shards that
    then failed their checksums: while another process holds the folder's lock,
    a run is a usage error before it writes anything; once it ends, the folder
    is taken."""
    from tests.test_experiment import holding

    out = tmp_path / "run"
    out.mkdir()
    with holding(out):
        with pytest.raises(SystemExit) as stopped:
            generate.main([*RUN, "--out", str(out)])
        assert stopped.value.code == 2
        assert "another tasks.generate run is writing to" in capsys.readouterr().err
        assert list(out.iterdir()) == []
        # the same, found by generate itself (a run that took it after prepare)
        config = generate.parse_config([*RUN, "--out", str(out)])
        prepared = generate.prepare(dataclasses.replace(config, out=tmp_path / "x"))
        with pytest.raises(generate.BusyError):
            generate.generate(config, prepared=prepared)
        assert list(out.iterdir()) == []
    generate.main([*RUN, "--out", str(out)])
    shards.Dataset(out).verify()


# A generation process sent SIGTERM, by itself alone (`kill PID`, not the
# process group): as its first shards have just been handed to the pool
# ("running"), or as the pool's manager thread begins to read a finished
# shard, which its worker is still sending ("sending": the manager waits a
# second before it reads).
_TERMINATE_THE_RUN = """
import os, signal, sys, threading, time
from multiprocessing import connection
from tasks import generate

MOMENT, owner = sys.argv[1], os.getpid()
wait, recv = generate.cf.wait, connection.Connection.recv

def terminate_then_wait(futures, **kwargs):
    if MOMENT == "running":
        os.kill(owner, signal.SIGTERM)
    return wait(futures, **kwargs)

def terminate_then_receive(self, sent=[]):
    if MOMENT == "sending" and not sent and threading.current_thread() is not (
        threading.main_thread()
    ):
        sent.append(os.kill(owner, signal.SIGTERM))
        time.sleep(1)  # the run ends the workers, one of them halfway through
    return recv(self)

generate.cf.wait = terminate_then_wait
connection.Connection.recv = terminate_then_receive
generate.main(sys.argv[2:])
"""


@pytest.mark.parametrize(
    "moment, episodes",
    [("running", ["100000"]), ("sending", ["5", "--max-steps", "2000"])],
    ids=["running", "sending"],
)
def test_sigterm_to_the_run_alone_ends_its_running_shards_with_it(
    tmp_path, moment, episodes
):
    """A SIGTERM to the run's process alone (its pool's workers are not sent
    it) printed the stop line, and then the run waited to exit until its
    workers had finished the shards they were running, whose results it
    discards (here two shards of 100,000 episodes each, hours). It ends them
    with the run. A worker ended while it sent its shard left part of it in the
    pipe, and the run hung at exit for ever (a shard of 5 episodes of 2,000
    steps here, hundreds of kB). The timeout is a guard against those waits,
    not a timing check."""
    argv = [
        "--domain", "acrobot", "--instances", "2", "--shard-size", "1",
        "--policy", "random", "--no-progress", "--workers", "2",
        "--episodes-per-instance", *episodes,
    ]  # fmt: skip
    out = tmp_path / "terminated"
    run = subprocess.run(
        [sys.executable, "-c", _TERMINATE_THE_RUN, moment, *argv, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 143, run.stderr
    resume = shlex.join(["python", "-m", "tasks.generate", *argv, "--out", str(out)])
    assert run.stderr == (  # the one line: no traceback of the ended workers
        f"python -m tasks.generate: terminated: 0 of 2 shards finished are kept in "
        f"{out}; resume with the same command plus --resume: {resume} --resume\n"
    )
    assert [e["sha256"] for e in shards.read_manifest(out)["shards"]] == [None] * 2
