#!/usr/bin/env python3
"""Tests of the Ray Tune launcher, against real Ray and real `gaitscope train` runs (CI runs them
after `make test`: `make test-sweeps`).

    sweeps/test_sweep.py [--gaitscope BIN] [unittest args, e.g. -k smoke]

Each test writes a spec into a temporary folder, runs `sweeps/sweep.py` as a user would (a
subprocess), and checks what it left: summary.json, the run folders, Tune's results, the logs.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import unittest
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SWEEP = ROOT / "sweeps" / "sweep.py"
GAITSCOPE = Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target")) / "release" / "gaitscope"
# Short runs: updates start early so every trial trains and checkpoints several times.
SHORT = "steps = {steps}\ncheckpoint_every = 500\nlearning_starts = 100\neval_episodes = {eval}\n"
ENV = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "PYTHONUNBUFFERED": "1"}


def write_spec(folder: Path, text: str) -> Path:
    path = folder / "spec.toml"
    path.write_text(text)
    return path


def sweep(spec: Path, storage: Path, *extra: str) -> subprocess.Popen:
    # Its own session, so a test can interrupt the driver the way Ctrl+C in a terminal does.
    return subprocess.Popen([sys.executable, str(SWEEP), str(spec), "--storage", str(storage),
                             "--gaitscope", str(GAITSCOPE), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV,
                            start_new_session=True)


def finish(process: subprocess.Popen, timeout: float = 600) -> tuple[int, str]:
    out, _ = process.communicate(timeout=timeout)
    return process.returncode, out


def steps_saved(run: Path) -> int:
    try:
        return json.loads((run / "checkpoint.json").read_text())["steps_done"]
    except (OSError, ValueError, KeyError):
        return 0


def trainers_of(run: Path) -> list[int]:
    """Pids of the `gaitscope train` processes writing to `run` (read from /proc)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"train" in argv and str(run).encode() in argv:
            pids.append(int(proc.name))
    return pids


def wait_for(what: str, condition, process: subprocess.Popen, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"the sweep exited ({process.returncode}) before {what}:\n{process.stdout.read()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def global_steps(run: Path) -> list[int]:
    return [json.loads(line)["global_step"] for line in (run / "metrics.jsonl").read_text().splitlines()]


def summary(storage: Path) -> dict[str, dict]:
    trials = json.loads((storage / "summary.json").read_text())["trials"]
    return {Path(t["checkpoint"]).name: t for t in trials}


class Sweeps(unittest.TestCase):
    def setUp(self) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="gaitscope-sweep-"))
        self.storage = self.tmp / "storage"
        self.addCleanup(shutil.rmtree, self.tmp, ignore_errors=True)

    def test_bad_specs_are_refused_before_anything_starts(self) -> None:
        cases = {
            'bogus_flag = 3\n[grid]\nseed = [0]\n': "unknown key 'bogus_flag'",
            '[grid]\nencoder = ["none", "transformer"]\n': "no encoder 'transformer'",
            '[grid]\n"damage.threshhold" = [20.0]\n': "the config from the grid's dotted keys is not a valid gaitscope config: unknown field `threshhold`",
            '[grid]\n"damage.threshold" = [-5.0]\n': "damage.threshold in (0, 1e12] (got 1, 0.1, -5)",
            'learning_starts = "soon"\n[grid]\nseed = [0]\n': "invalid value 'soon' for '--learning-starts",
            'out = "elsewhere"\n[grid]\nseed = [0]\n': "set by the launcher",
            'cpus_per_trial = 0\n[grid]\nseed = [0]\n': "cpus_per_trial must be an integer",
            '[grid]\nseed = []\n': "non-empty list",
            '[grid\nseed = [0]\n': "Expected ']' at the end of a table",
            '[search]\n"damage.threshold" = {loguniform = [0.0, 50.0]}\n': "loguniform needs [low, high] with low < high and low > 0",
            '[search]\n"damage.threshold" = {normal = [30.0, 5.0]}\n': "needs one of choice, loguniform, randint, uniform",
            '[search]\n"context.len" = {randint = [8, 8]}\n': "randint needs [low, high]",
            '[search]\n"context.len" = {randint = [0, 8]}\n': "context.len must lie in 1..=1024",
            'search_alg = "optuna"\n[grid]\nseed = [0]\n': "move the [grid] keys there as choice",
            'metric = "reward"\n[grid]\nseed = [0]\n': "metric 'reward' is not reported",
            '[grid]\nz_dim = [0]\n': "z size",
            '[grid]\nencoder = ["none"]\naux = ["dynamics"]\n': "not --encoder none",
            '[grid]\naux_weight = [2.0]\n': "--aux-weight needs --aux dynamics",
            '[grid]\naux = ["reconstruction"]\n': "invalid value 'reconstruction' for '--aux",
        }
        for body, reason in cases.items():
            with self.subTest(body=body):
                spec = write_spec(self.tmp, 'name = "bad"\nsteps = 1000\n' + body)
                code, out = finish(sweep(spec, self.storage), timeout=120)
                self.assertEqual(code, 2, out)
                self.assertIn("sweep: refused", out)
                self.assertIn(reason, out)
                self.assertFalse(self.storage.exists(), "nothing may be written for a refused spec")

    def test_shipped_specs_pass_the_checks(self) -> None:
        sys.path.insert(0, str(SWEEP.parent))
        import sweep as launcher

        specs = sorted((ROOT / "sweeps").glob("*.toml"))
        self.assertGreaterEqual(len(specs), 4)
        for path in specs:
            with self.subTest(spec=path.name):
                spec = launcher.load_spec(path, str(GAITSCOPE))
                launcher.check_trials(str(GAITSCOPE), spec)

    def test_smoke_sweep_trains_reports_and_evaluates(self) -> None:
        spec = write_spec(self.tmp, 'name = "smoke"\n' + SHORT.format(steps=2000, eval=2)
                          + '[grid]\nencoder = ["none", "lstm"]\n')
        code, out = finish(sweep(spec, self.storage))
        self.assertEqual(code, 0, out)
        trials = summary(self.storage)
        self.assertEqual(set(trials), {"baseline-s0", "encoder-lstm-s0"})
        for name, t in trials.items():
            self.assertEqual(t["steps_done"], 2000, name)
            self.assertTrue(t["finished"], name)
            self.assertEqual(t["attempts"], 1, name)
            self.assertEqual(steps_saved(Path(t["checkpoint"])), 2000, name)
            self.assertIsNotNone(t["success_rate"], name)
        # Both final checkpoints went through `gaitscope eval --episodes 2`, as one group.
        report = json.loads((self.storage / "eval" / "default" / "eval.json").read_text())
        self.assertEqual(report["episodes_per_cell"], 2)
        self.assertEqual({c["model"] for c in report["cells"]}, set(trials))
        # Tune's own loggers: CSV, JSON and TensorBoard event files in every trial folder.
        trial_dirs = [d for d in (self.storage / "tune").iterdir() if d.is_dir() and d.name.startswith("trainable")]
        self.assertEqual(len(trial_dirs), 2)
        for d in trial_dirs:
            self.assertTrue((d / "progress.csv").exists(), d)
            self.assertTrue((d / "result.json").exists(), d)
            self.assertTrue(list(d.glob("events.out.tfevents.*")), d)
            last = json.loads((d / "result.json").read_text().splitlines()[-1])
            self.assertIn(Path(last["run"]).name, trials, "Tune's results name the trial's run")

    def test_a_search_space_sampled_by_optuna_under_asha(self) -> None:
        spec = write_spec(self.tmp, 'name = "search"\nnum_samples = 2\nsearch_alg = "optuna"\n'
                          'metric = "episodic_return"\n' + SHORT.format(steps=1500, eval=0)
                          + '[search]\nencoder = {choice = ["none"]}\n'
                          '"damage.threshold" = {uniform = [20.0, 50.0]}\n'
                          'z_dim = {choice = [16, 32]}\n"context.len" = {randint = [8, 17]}\n'
                          '[scheduler]\ngrace_period = 500\n')
        code, out = finish(sweep(spec, self.storage))
        self.assertEqual(code, 0, out)
        trials = json.loads((self.storage / "summary.json").read_text())["trials"]
        self.assertEqual(len(trials), 2)
        self.assertEqual(len({t["checkpoint"] for t in trials}), 2, "two samples, two run folders")
        for t in trials:
            c = t["config"]
            self.assertTrue(20.0 <= c["damage.threshold"] <= 50.0 and 8 <= c["context.len"] < 17, c)
            self.assertIn(c["z_dim"], (16, 32))
            # The sampled values reached the run: its checkpoint holds them.
            meta = json.loads((Path(t["checkpoint"]) / "checkpoint.json").read_text())
            self.assertEqual(meta["net"]["context_len"], c["context.len"])
            self.assertEqual(meta["net"]["z_dim"], c["z_dim"])
            self.assertEqual(meta["env"]["damage"]["threshold"], c["damage.threshold"])
            # ASHA may stop a trial early: then it is finished, and says so.
            self.assertTrue(t["finished"])
            self.assertEqual(t["stopped_early"], t["steps_done"] < 1500)

    def test_a_killed_trial_is_retried_from_its_last_checkpoint(self) -> None:
        spec = write_spec(self.tmp, 'name = "fault"\n' + SHORT.format(steps=2000, eval=0)
                          + '[grid]\nencoder = ["none"]\n')
        run = self.storage / "runs" / "default" / "baseline-s0"
        process = sweep(spec, self.storage)
        wait_for("the first checkpoint", lambda: steps_saved(run) >= 500, process)
        killed_at = steps_saved(run)
        (pid,) = trainers_of(run)
        os.kill(pid, signal.SIGKILL)
        code, out = finish(process)
        self.assertEqual(code, 0, out)
        t = summary(self.storage)["baseline-s0"]
        self.assertEqual((t["steps_done"], t["attempts"]), (2000, 2))
        log = (run.parent / "baseline-s0.log").read_text().splitlines()
        attempts = [line for line in log if line.startswith("sweep: attempt")]
        self.assertEqual(len(attempts), 2, log)
        self.assertIn(f"--resume {run}", attempts[1])
        # The resumed run continued from the checkpoint: the metrics never go back to step 0,
        # and the steps after the checkpoint are logged once (the resume cut the killed tail).
        steps = global_steps(run)
        self.assertEqual(steps, sorted(steps))
        self.assertEqual(steps_saved(run), 2000)
        # What Tune saw: the retry's first report is at the killed run's checkpoint, not at 0.
        (trial_dir,) = [d for d in (self.storage / "tune").iterdir() if d.name.startswith("trainable")]
        with (trial_dir / "progress.csv").open() as f:
            retried = [int(r["steps_done"]) for r in csv.DictReader(f) if r["attempt"] == "2"]
        self.assertTrue(retried, "the retry reported to Tune")
        self.assertGreaterEqual(min(retried), killed_at)

    def test_an_interrupted_sweep_resumes_without_redoing_finished_trials(self) -> None:
        spec = write_spec(self.tmp, 'name = "restore"\nmax_concurrent_trials = 1\n'
                          + SHORT.format(steps=1500, eval=0) + '[grid]\nencoder = ["none"]\nseed = [0, 1]\n')
        runs = [self.storage / "runs" / "default" / f"baseline-s{s}" for s in (0, 1)]
        process = sweep(spec, self.storage)

        def one_done_one_started() -> bool:
            saved = sorted(steps_saved(r) for r in runs)
            return saved[0] >= 500 and saved[1] == 1500 and not any(
                trainers_of(r) for r in runs if steps_saved(r) == 1500)

        wait_for("one trial finished and the other checkpointed", one_done_one_started, process)
        finished_run = max(runs, key=steps_saved)
        interrupted_run = min(runs, key=steps_saved)
        finished_metrics = (finished_run / "metrics.jsonl").read_bytes()
        os.kill(process.pid, signal.SIGINT)  # Ctrl+C on the driver
        code, out = finish(process, timeout=120)
        self.assertNotEqual(code, 0, "an interrupted sweep has not finished every trial")
        deadline = time.monotonic() + 30
        while trainers_of(interrupted_run) and time.monotonic() < deadline:
            time.sleep(0.2)
        self.assertEqual(trainers_of(interrupted_run), [], "no trainer outlives the sweep")

        code, out = finish(sweep(spec, self.storage, "--resume"))
        self.assertEqual(code, 0, out)
        trials = summary(self.storage)
        self.assertEqual({t["steps_done"] for t in trials.values()}, {1500})
        self.assertEqual(trials[finished_run.name]["attempts"], 1, "a finished trial is not run again")
        self.assertEqual((finished_run / "metrics.jsonl").read_bytes(), finished_metrics)
        self.assertEqual(trials[interrupted_run.name]["attempts"], 2)
        log = (interrupted_run.parent / f"{interrupted_run.name}.log").read_text()
        self.assertIn(f"--resume {interrupted_run}", log)
        steps = global_steps(interrupted_run)
        self.assertEqual(steps, sorted(steps))

    def test_a_two_node_cluster_runs_trials_on_both_nodes(self) -> None:
        from ray.cluster_utils import Cluster

        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        try:
            worker = cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
            nodes = {cluster.head_node.node_id, worker.node_id}
            spec = write_spec(self.tmp, 'name = "cluster"\n' + SHORT.format(steps=1000, eval=0)
                              + '[grid]\nencoder = ["none"]\nseed = [0, 1]\n')
            # --ship: the binary reaches the nodes through Ray's runtime_env, not this checkout.
            code, out = finish(sweep(spec, self.storage, "--address", cluster.address, "--ship"))
            self.assertEqual(code, 0, out)
            trials = summary(self.storage)
            self.assertEqual({t["steps_done"] for t in trials.values()}, {1000})
            self.assertEqual({t["node"] for t in trials.values()}, nodes, "one trial on each node")
            for name in trials:
                log = (self.storage / "runs" / "default" / f"{name}.log").read_text()
                binary = log.split(": ", 2)[2].split()[0]
                self.assertNotEqual(Path(binary), GAITSCOPE)
                self.assertIn("runtime_resources", binary, "the copy Ray unpacked on the node")
        finally:
            cluster.shutdown()


if __name__ == "__main__":
    if "--gaitscope" in sys.argv:
        i = sys.argv.index("--gaitscope")
        GAITSCOPE = Path(sys.argv[i + 1]).resolve()
        del sys.argv[i:i + 2]
    if not GAITSCOPE.exists():
        sys.exit(f"test_sweep: no {GAITSCOPE}; build it first (cargo build --release)")
    unittest.main(verbosity=2)
