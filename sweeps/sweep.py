#!/usr/bin/env python3
"""Runs a gaitscope sweep on Ray Tune: every trial is `gaitscope train` in a subprocess.

    sweeps/sweep.py SPEC.toml [--storage DIR] [--address ADDR] [--resume] [--gaitscope BIN]

A spec (TOML) names the trial set and the training flags; see docs/sweeps.md. Before anything
starts, every trial's options are checked by `gaitscope train --check`, so a bad key or value
is refused with gaitscope's own reason. Each trial follows its run's metrics.jsonl and reports
to Tune; every gaitscope checkpoint save becomes a Tune checkpoint (a pointer to the run
folder: the run itself, replay buffer included, stays where gaitscope wrote it). A retried
trial (FailureConfig) resumes its run with `gaitscope train --resume`. The end writes
STORAGE/summary.json and runs `gaitscope eval` on the final checkpoints, grouped by model.
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import signal
import itertools
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# Spec keys that are not `gaitscope train` flags.
SPEC_KEYS = {"name", "steps", "grid", "search", "num_samples", "search_alg", "metric", "mode", "scheduler",
             "cpus_per_trial", "max_failures", "max_concurrent_trials", "eval_episodes"}
# Train flags a spec may not set: the launcher owns them.
OWNED_FLAGS = {"out", "resume", "steps", "config", "quiet", "check", "encoder", "seed"}
MODEL_NAMES = {"none": "baseline", "lstm": "encoder-lstm", "mlp-window": "encoder-mlp"}
# What a trial reports, so what a scheduler or search algorithm may optimise.
METRICS = {"success_rate", "episodic_return", "steps_done", "global_step", "steps_per_s", "episodes"}
# [search] distributions: name → how its arguments must look.
DISTRIBUTIONS = {"uniform", "loguniform", "randint", "choice"}
SEARCH_ALGS = {"random", "optuna"}
# How many of the latest episodes the reported success rate and return average over.
RECENT_EPISODES = 20


class SpecError(Exception):
    pass


def train_flags(gaitscope: str) -> dict[str, bool]:
    """The long flags `gaitscope train` takes (name → takes a value), read from its --help."""
    text = subprocess.run([gaitscope, "train", "--help"], capture_output=True, text=True, check=True).stdout
    flags = {}
    for m in re.finditer(r"^\s+(?:-\w, )?--([a-z0-9-]+)( <[A-Z_|]+>)?", text, re.M):
        flags[m.group(1)] = bool(m.group(2))
    return flags


def load_spec(path: Path, gaitscope: str) -> dict:
    try:
        spec = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise SpecError(f"{path}: {e}") from None
    flags = train_flags(gaitscope)
    for key in spec:
        flag = key.replace("_", "-")
        if key in SPEC_KEYS:
            continue
        if flag in OWNED_FLAGS:
            raise SpecError(f"{path}: '{key}' is set by the launcher (use [grid] for encoder and seed)")
        if flag not in flags:
            known = ", ".join(sorted(k.replace("-", "_") for k in flags if k not in OWNED_FLAGS and k != "help"))
            raise SpecError(f"{path}: unknown key '{key}' (spec keys: {', '.join(sorted(SPEC_KEYS))}; train flags: {known})")
    for required in ("name", "steps"):
        if required not in spec:
            raise SpecError(f"{path}: missing '{required}'")
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", str(spec["name"])):
        raise SpecError(f"{path}: name '{spec['name']}' must be letters, digits, '.', '_' or '-'")
    if not isinstance(spec["steps"], int) or spec["steps"] < 1:
        raise SpecError(f"{path}: steps must be a positive integer, got {spec['steps']!r}")
    for key, least in (("cpus_per_trial", 1), ("max_concurrent_trials", 1), ("eval_episodes", 0), ("max_failures", -1)):
        value = spec.get(key, least)
        if not isinstance(value, int) or isinstance(value, bool) or value < least:
            raise SpecError(f"{path}: {key} must be an integer ≥ {least}, got {value!r}")
    grid, search = spec.setdefault("grid", {}), spec.setdefault("search", {})
    if not isinstance(grid, dict) or not isinstance(search, dict) or not (grid or search):
        raise SpecError(f"{path}: [grid] or [search] must list at least one key")
    for key, values in grid.items():
        trial_key(path, key, flags)
        if not isinstance(values, list) or not values:
            raise SpecError(f"{path}: grid key '{key}' needs a non-empty list of values")
    for key, dist in search.items():
        trial_key(path, key, flags)
        if key in grid:
            raise SpecError(f"{path}: '{key}' is in both [grid] and [search]")
        check_distribution(path, key, dist)
    encoders = grid.get("encoder") or search.get("encoder", {}).get("choice") or ["lstm"]
    for encoder in encoders:
        if encoder not in MODEL_NAMES:
            raise SpecError(f"{path}: no encoder '{encoder}' (gaitscope has {', '.join(MODEL_NAMES)})")
    samples = spec.get("num_samples", 1)
    if not isinstance(samples, int) or isinstance(samples, bool) or samples < 1:
        raise SpecError(f"{path}: num_samples must be an integer ≥ 1, got {samples!r}")
    if spec.get("search_alg", "random") not in SEARCH_ALGS:
        raise SpecError(f"{path}: search_alg '{spec['search_alg']}' is not one of {', '.join(sorted(SEARCH_ALGS))}")
    if spec.get("search_alg") == "optuna" and grid:
        raise SpecError(f"{path}: search_alg 'optuna' samples [search] only; move the [grid] keys there as choice")
    for table in (spec, spec.get("scheduler", {})):
        if table.get("metric", "success_rate") not in METRICS:
            raise SpecError(f"{path}: metric '{table['metric']}' is not reported (trials report {', '.join(sorted(METRICS))})")
        if table.get("mode", "max") not in ("max", "min"):
            raise SpecError(f"{path}: mode must be 'max' or 'min', got {table['mode']!r}")
    spec["_flags"] = flags
    return spec


def check_distribution(path: Path, key: str, dist) -> None:
    """A [search] value: exactly one of {uniform|loguniform|randint = [low, high]} or {choice = [...]}."""
    if not isinstance(dist, dict) or len(dist) != 1 or next(iter(dist)) not in DISTRIBUTIONS:
        raise SpecError(f"{path}: search key '{key}' needs one of {', '.join(sorted(DISTRIBUTIONS))}, "
                        f"e.g. {{uniform = [20.0, 50.0]}}; got {dist!r}")
    (kind, args), = dist.items()
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise SpecError(f"{path}: search key '{key}': choice needs a non-empty list")
        return
    number = int if kind == "randint" else (int, float)
    ok = (isinstance(args, list) and len(args) == 2
          and all(isinstance(a, number) and not isinstance(a, bool) for a in args)
          and args[0] < args[1] and (kind != "loguniform" or args[0] > 0))
    if not ok:
        raise SpecError(f"{path}: search key '{key}': {kind} needs [low, high] with low < high"
                        + (" and low > 0" if kind == "loguniform" else "")
                        + (", integers (high excluded)" if kind == "randint" else "") + f"; got {args!r}")


def trial_key(path: Path, key: str, flags: dict[str, bool]) -> None:
    """A grid or search key: encoder, seed, a dotted config key, or a train flag by its name."""
    if key in ("encoder", "seed") or "." in key:
        return
    flag = key.replace("_", "-")
    if flag in OWNED_FLAGS or flag not in flags or not flags[flag]:
        raise SpecError(f"{path}: trial key '{key}' is not encoder, seed, a dotted config key "
                        f"(damage.threshold) or a train flag that takes a value")


def trials(spec: dict) -> list[dict]:
    """The trials `gaitscope train --check` vets before anything starts: the grid's cross
    product, each with the search space at its lows, at its highs, and at every choice."""
    keys = list(spec["grid"])
    points = [dict(zip(keys, values)) for values in itertools.product(*(spec["grid"][k] for k in keys))]
    corners = [{}]
    if spec["search"]:
        low, high, first = {}, {}, {}
        for key, dist in spec["search"].items():
            (kind, args), = dist.items()
            if kind == "choice":
                first[key] = args[0]
            else:  # randint's high is excluded
                low[key], high[key] = args[0], args[1] - 1 if kind == "randint" else args[1]
        corners = [{**low, **first}, {**high, **first}] + [
            {**low, **first, key: value}
            for key, dist in spec["search"].items() if "choice" in dist for value in dist["choice"]]
    unique = {json.dumps({**p, **c}, sort_keys=True): {**p, **c} for p in points for c in corners}
    return list(unique.values())


def nested_config(point: dict) -> dict:
    """Dotted grid keys (`damage.threshold`) as the nested JSON `gaitscope train --config` reads."""
    config: dict = {}
    for key, value in point.items():
        if "." not in key:
            continue  # encoder, seed and train flags go on the command line
        parts = key.split(".")
        node = config
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return config


def run_name(point: dict) -> tuple[str, str]:
    """(group, folder): runs that differ only in seed share a group; the folder names the model
    and seed the way `gaitscope eval` groups them (encoder-lstm-s1). A sampled value is shown to
    4 digits, and a hash of the exact values keeps two samples from ever sharing a folder."""
    rest = {k: v for k, v in sorted(point.items()) if k not in ("encoder", "seed")}
    group = "-".join(f"{k.split('.')[-1].replace('_', '')}{v:.4g}" if isinstance(v, float) else
                     f"{k.split('.')[-1].replace('_', '')}{v}" for k, v in rest.items()) or "default"
    if any(isinstance(v, float) and f"{v:.4g}" != repr(v) for v in rest.values()):
        group += "-" + hashlib.sha1(json.dumps(rest, sort_keys=True).encode()).hexdigest()[:6]
    model = MODEL_NAMES[point.get("encoder", "lstm")]
    return group, f"{model}-s{point.get('seed', 0)}"


def train_command(gaitscope: str, spec: dict, point: dict, config_file: Path) -> list[str]:
    cmd = [gaitscope, "train", "--quiet", "--steps", str(spec["steps"]), "--config", str(config_file),
           "--encoder", str(point.get("encoder", "lstm")), "--seed", str(point.get("seed", 0))]
    # One update thread per CPU the trial is given (gaitscope would otherwise use every core).
    if "threads" not in spec:
        cmd += ["--threads", str(spec.get("cpus_per_trial", 1))]
    for key, value in spec.items():
        if key in SPEC_KEYS or key.startswith("_"):
            continue
        flag = key.replace("_", "-")
        if spec["_flags"][flag]:
            cmd += [f"--{flag}", str(value)]
        elif value is True:
            cmd.append(f"--{flag}")
    # Train flags in the grid or search space (batch_size, z_dim, …), after the spec's own.
    for key, value in point.items():
        if key not in ("encoder", "seed") and "." not in key:
            cmd += [f"--{key.replace('_', '-')}", str(value)]
    return cmd


def check_trials(gaitscope: str, spec: dict) -> None:
    """Every trial's options through `gaitscope train --check`: gaitscope's own reasons."""
    with tempfile.TemporaryDirectory() as tmp:
        for i, point in enumerate(trials(spec)):
            config_file = Path(tmp) / f"config-{i}.json"
            config_file.write_text(json.dumps(nested_config(point)))
            cmd = train_command(gaitscope, spec, point, config_file) + ["--check", "--out", str(Path(tmp) / f"run-{i}")]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                reason = done.stderr.strip().removeprefix("error: ").replace(
                    f"config file {config_file}", "the config from the grid's dotted keys")
                raise SpecError(f"trial {point}: {reason}")


def follow(run: Path, process: subprocess.Popen, report) -> None:
    """Reads metrics.jsonl as it grows; reports every log line with the latest episode stats,
    and a Tune checkpoint whenever gaitscope saved one."""
    from ray import tune

    metrics = run / "metrics.jsonl"
    offset = 0
    lines: list[str] = []
    episodes: list[tuple[float, bool]] = []
    latest: dict = {}
    saved_step = None
    while True:
        exited = process.poll() is not None
        lines = []
        if metrics.exists():
            with metrics.open() as f:
                f.seek(offset)
                lines = f.readlines()
                # A line still being written waits for the next pass.
                if lines and not lines[-1].endswith("\n"):
                    lines.pop()
                offset += sum(len(line.encode()) for line in lines)
            for line in lines:
                row = json.loads(line)
                if "charts/episodic_return" in row:
                    episodes.append((row["charts/episodic_return"], bool(row.get("charts/success"))))
                    del episodes[:-RECENT_EPISODES]
                latest.update({k: v for k, v in row.items() if isinstance(v, (int, float))})
        meta = run / "checkpoint.json"
        step = None
        if meta.exists():
            try:
                step = json.loads(meta.read_text())["steps_done"]
            except (json.JSONDecodeError, KeyError, OSError):
                step = None  # mid-rename: next pass
        saved = step is not None and step != saved_step
        if lines or saved:
            result = {
                "steps_done": step if step is not None else 0,
                "global_step": latest.get("global_step", 0),
                "steps_per_s": latest.get("charts/SPS", 0.0),
                "episodes": len(episodes),
            }
            # NaN until the first episode ends: schedulers and searchers see the key in every
            # result (Optuna needs it), and a NaN never wins a comparison.
            result["episodic_return"] = sum(r for r, _ in episodes) / len(episodes) if episodes else math.nan
            result["success_rate"] = sum(s for _, s in episodes) / len(episodes) if episodes else math.nan
            if saved:
                saved_step = step
                with tempfile.TemporaryDirectory() as tmp:
                    (Path(tmp) / "run.json").write_text(json.dumps({"run": str(run), "steps_done": step}))
                    report(result, checkpoint=tune.Checkpoint.from_directory(tmp))
            else:
                report(result)
        if exited:
            return
        time.sleep(1.0)


def die_with_parent() -> None:
    """Runs in the child before exec: the kernel kills `gaitscope train` when the Ray worker that
    started it dies, so a lost worker never leaves a second writer in the run folder."""
    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def stage_binary(gaitscope: str, stage: Path) -> Path:
    """The binary and the libmujoco it links, in one folder for Ray's runtime_env (`--ship`): a
    copy without debug info (a tenth of the size), the library beside it in lib/."""
    stage.mkdir(parents=True, exist_ok=True)
    (stage / "lib").mkdir(exist_ok=True)
    if not shutil.which("strip") or subprocess.run(
            ["strip", "--strip-debug", "-o", str(stage / "gaitscope"), gaitscope]).returncode != 0:
        shutil.copy2(gaitscope, stage / "gaitscope")
    linked = subprocess.run(["ldd", gaitscope], capture_output=True, text=True, check=True).stdout
    # ldd's lines read "libmujoco.so.3.17.0 => /path/libmujoco.so.3.17.0 (0x...)".
    libs = [line.split("=>")[1].split("(")[0].strip()
            for line in linked.splitlines() if "libmujoco" in line and "=>" in line]
    if not libs or not Path(libs[0]).exists():
        raise SpecError(f"--ship: cannot find the libmujoco that {gaitscope} links (run `make setup`)")
    shutil.copy2(libs[0], stage / "lib" / Path(libs[0]).name)
    return stage


def make_trainable(gaitscope: str, spec: dict, runs: Path, shipped: bool):
    def trainable(point: dict) -> None:
        import ray
        from ray import tune

        env = None
        binary = gaitscope
        if shipped:
            # Ray unpacked the staged folder as this worker's working directory (no chdir to the
            # trial folder: the driver set RAY_CHDIR_TO_TRIAL_DIR=0).
            here = Path.cwd()
            binary = str(here / "gaitscope")
            env = {**os.environ, "LD_LIBRARY_PATH": str(here / "lib")}
        group, folder = run_name(point)
        run = runs / group / folder
        run.parent.mkdir(parents=True, exist_ok=True)
        config_file = run.parent / f"{folder}.config.json"
        config_file.write_text(json.dumps(nested_config(point)))
        cmd = train_command(binary, spec, point, config_file)
        # A retried trial (or one restored with the sweep) continues its run, not from step 0.
        if (run / "checkpoint.json").exists():
            cmd += ["--resume", str(run)]
        else:
            cmd += ["--out", str(run)]
        node = ray.get_runtime_context().get_node_id()
        # Attempts of this run, over retries and restores: 1 when nothing ever failed.
        attempts_file = run.parent / f"{folder}.attempts"
        attempt = int(attempts_file.read_text() or 0) + 1 if attempts_file.exists() else 1
        attempts_file.write_text(str(attempt))
        log = open(run.parent / f"{folder}.log", "a")
        log.write(f"sweep: attempt {attempt} on node {node}: {' '.join(cmd)}\n")
        log.flush()
        process = subprocess.Popen(cmd, stdout=log, stderr=log, preexec_fn=die_with_parent, env=env)

        def report(result, **kw):
            # The run lives outside Tune's trial folder (the layout eval groups by, the same across
            # restores): every result names it.
            tune.report({**result, "attempt": attempt, "node": node, "run": str(run)}, **kw)

        try:
            follow(run, process, report)
        finally:
            if process.poll() is None:
                process.kill()
            process.wait()
            log.close()
        if process.returncode != 0:
            raise RuntimeError(f"gaitscope train exited with {process.returncode} (log: {log.name})")
        return None

    return trainable


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("spec", type=Path)
    parser.add_argument("--storage", type=Path, help="default: runs/sweeps/NAME")
    parser.add_argument("--address", help="a running Ray cluster (e.g. auto); default: a local one")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted sweep in STORAGE")
    parser.add_argument("--gaitscope", default=str(ROOT / "target/release/gaitscope"))
    parser.add_argument("--ship", action="store_true",
                        help="send the binary and libmujoco to every node with Ray's runtime_env "
                             "(for nodes without this checkout at the same path)")
    args = parser.parse_args()
    gaitscope = str(Path(args.gaitscope).resolve())
    try:
        spec = load_spec(args.spec, gaitscope)
        check_trials(gaitscope, spec)
    except SpecError as e:
        print(f"sweep: refused: {e}", file=sys.stderr)
        return 2

    import ray
    from ray import tune

    storage = (args.storage or ROOT / "runs/sweeps" / spec["name"]).resolve()
    runs = storage / "runs"
    storage.mkdir(parents=True, exist_ok=True)
    runtime_env = None
    if args.ship:
        try:
            runtime_env = {"working_dir": str(stage_binary(gaitscope, storage / "ship"))}
        except SpecError as e:
            print(f"sweep: refused: {e}", file=sys.stderr)
            return 2
        os.environ["RAY_CHDIR_TO_TRIAL_DIR"] = "0"  # Tune passes it on to the trainables
    ray.init(address=args.address, include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
    trainable = tune.with_resources(make_trainable(gaitscope, spec, runs, args.ship),
                                    {"cpu": spec.get("cpus_per_trial", 1)})
    experiment = storage / "tune"
    if args.resume and tune.Tuner.can_restore(str(experiment)):
        tuner = tune.Tuner.restore(str(experiment), trainable, resume_errored=True)
    else:
        scheduler = None
        if "scheduler" in spec:
            s = spec["scheduler"]
            scheduler = tune.schedulers.ASHAScheduler(
                time_attr="global_step", metric=s.get("metric", spec.get("metric", "success_rate")),
                mode=s.get("mode", spec.get("mode", "max")),
                grace_period=s.get("grace_period", spec["steps"] // 10), max_t=spec["steps"])
        param_space = {k: tune.grid_search(v) for k, v in spec["grid"].items()}
        for key, dist in spec["search"].items():
            (kind, args), = dist.items()
            param_space[key] = tune.choice(args) if kind == "choice" else getattr(tune, kind)(*args)
        search_alg = None
        if spec.get("search_alg") == "optuna":
            from ray.tune.search.optuna import OptunaSearch

            search_alg = OptunaSearch(metric=spec.get("metric", "success_rate"), mode=spec.get("mode", "max"))
        tuner = tune.Tuner(
            trainable,
            param_space=param_space,
            tune_config=tune.TuneConfig(scheduler=scheduler, search_alg=search_alg,
                                        num_samples=spec.get("num_samples", 1),
                                        # A stopped trial's worker exits, and its trainer with it.
                                        reuse_actors=False,
                                        max_concurrent_trials=spec.get("max_concurrent_trials")),
            run_config=tune.RunConfig(
                name="tune",
                storage_path=str(storage),
                failure_config=tune.FailureConfig(max_failures=spec.get("max_failures", 3)),
            ),
        )
    results = tuner.fit()

    summary = {"spec": spec["name"], "trials": []}
    finished = True
    for result in results:
        point = result.config
        group, folder = run_name(point)
        run = runs / group / folder
        metrics = result.metrics or {}
        # Under a scheduler a trial may end early by its decision (ASHA): that is finished too.
        stopped_early = result.error is None and "scheduler" in spec and metrics.get("steps_done", 0) < spec["steps"]
        ok = result.error is None and (metrics.get("steps_done") == spec["steps"] or stopped_early)
        finished &= ok
        summary["trials"].append({
            "encoder": point.get("encoder", "lstm"),
            "seed": point.get("seed", 0),
            "config": point,
            "steps_done": metrics.get("steps_done", 0),
            "checkpoint": str(run),
            "success_rate": metrics.get("success_rate"),
            "episodic_return": metrics.get("episodic_return"),
            "finished": ok,
            "stopped_early": stopped_early,
            "attempts": metrics.get("attempt"),
            "node": metrics.get("node"),
            "error": None if result.error is None else str(result.error),
        })
    (storage / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"sweep: {len(summary['trials'])} trials → {storage / 'summary.json'}")

    # eval_episodes = 0 skips the evaluation; unset, gaitscope eval's own default applies.
    episodes = spec.get("eval_episodes")
    if finished and episodes != 0:
        groups: dict[str, list[str]] = {}
        for t in summary["trials"]:
            groups.setdefault(Path(t["checkpoint"]).parent.name, []).append(t["checkpoint"])
        for group, dirs in groups.items():
            cmd = [gaitscope, "eval", "--checkpoint", *dirs, "--out", str(storage / "eval" / group)]
            if episodes is not None:
                cmd += ["--episodes", str(episodes)]
            if subprocess.run(cmd).returncode != 0:
                print(f"sweep: gaitscope eval failed on group {group}", file=sys.stderr)
                return 1
    return 0 if finished else 1


if __name__ == "__main__":
    sys.exit(main())
