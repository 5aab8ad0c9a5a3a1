//! `gaitscope bench …`.

use anyhow::{Result, bail};
use clap::Subcommand;
use std::path::PathBuf;

use super::values::{EncoderArg, UpdateArg};
use gaitscope::Condition;
use gaitscope::bench::bench_env;

use super::EnvArgs;

#[derive(Subcommand)]
pub(crate) enum BenchCommand {
    /// Env steps/s with random actions against bare MuJoCo on the same model.
    Env {
        #[arg(long, default_value_t = 20_000)]
        steps: usize,
        #[arg(long, default_value_t = 5)]
        runs: usize,
        #[command(flatten)]
        env: EnvArgs,
    },
    /// Telemetry cost: steps/s recorded to .rrd vs the same rollout without, bytes per step, memory.
    Record {
        /// Full-length (500-step) episodes to run each way.
        #[arg(long, default_value_t = 20)]
        episodes: usize,
    },
    /// Live loop: how far the simulation keeps up with real time at 1× and 8× (headless, with
    /// telemetry to a file), for a checkpoint alone and side by side with a second one.
    Live {
        #[arg(long, value_name = "DIR", default_value = "checkpoints/encoder-lstm")]
        checkpoint: PathBuf,
        #[arg(long, value_name = "DIR", default_value = "checkpoints/baseline")]
        compare: PathBuf,
        /// Seconds per measurement.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
    },
    /// Evaluation throughput: 100 episodes per condition (300 in all) of one checkpoint.
    Eval {
        #[arg(long, value_name = "DIR")]
        checkpoint: PathBuf,
        #[arg(long, default_value_t = 100)]
        episodes: usize,
    },
    /// Search throughput: candidates and episodes per second of `gaitscope search` (CMA-ES,
    /// severity budget 1, no reference, no shrinking) on one checkpoint.
    Search {
        #[arg(long, value_name = "DIR", default_value = "checkpoints/baseline")]
        checkpoint: PathBuf,
        #[arg(long, default_value_t = 48)]
        evaluations: usize,
        /// Episodes per candidate.
        #[arg(long, default_value_t = 16)]
        episodes: usize,
        #[arg(long, default_value_t = 1)]
        threads: usize,
    },
    /// Training env steps/s per encoder (one update per step) against the updates alone.
    Train {
        /// Learning steps to time per encoder (after a 1,000-step random warm-up).
        #[arg(long, default_value_t = 1_000)]
        steps: u64,
        #[arg(long, value_enum, num_args = 1.., default_values_t = [EncoderArg::None, EncoderArg::Lstm, EncoderArg::MlpWindow])]
        encoders: Vec<EncoderArg>,
        /// The update to time: fused (what `train` runs) or reference (candle's autograd).
        #[arg(long, value_enum, default_value_t = UpdateArg::Fused)]
        update: UpdateArg,
        /// Threads per fused update (1: per-core figures, comparable with the peers).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// One JSON object per encoder instead of the table.
        #[arg(long)]
        json: bool,
    },
}

/// `gaitscope bench …`.
pub(crate) fn bench_command(command: BenchCommand) -> Result<()> {
    match command {
        BenchCommand::Live {
            checkpoint,
            compare,
            seconds,
        } => {
            if !(seconds.is_finite() && seconds > 0.0) {
                bail!("--seconds must be a positive number");
            }
            for row in gaitscope::bench::bench_live(&checkpoint, &compare, seconds)? {
                println!("{row}");
            }
            Ok(())
        }
        BenchCommand::Env { steps, runs, env } => {
            if steps == 0 {
                bail!("--steps must be at least 1");
            }
            let report = bench_env(&env.load()?, steps, runs)?;
            println!("{report}");
            Ok(())
        }
        BenchCommand::Record { episodes } => {
            if episodes == 0 {
                bail!("--episodes must be at least 1");
            }
            let scratch =
                std::env::temp_dir().join(format!("gaitscope-bench-{}", std::process::id()));
            std::fs::create_dir_all(&scratch)?;
            let r = gaitscope::bench::bench_record(episodes, &scratch)?;
            let _ = std::fs::remove_dir_all(&scratch);
            println!(
                "{} steps: plain {:.0} steps/s, recorded {:.0} steps/s (telemetry {:.0} % of a recorded step), {:.0} bytes/step, RSS {:.0} → {:.0} MB",
                r.steps,
                r.plain_steps_per_s,
                r.recorded_steps_per_s,
                100.0 * r.telemetry_share(),
                r.bytes_per_step,
                r.rss_before_mb,
                r.rss_after_mb
            );
            Ok(())
        }
        BenchCommand::Eval {
            checkpoint,
            episodes,
        } => {
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
            let opts = gaitscope::eval::EvalOptions {
                checkpoints: vec![checkpoint],
                told_healthy: Vec::new(),
                episodes,
                seed_base: gaitscope::eval::EVAL_SEED_BASE,
                conditions: Condition::ALL.map(Into::into).to_vec(),
                scenarios: Vec::new(),
                max_steps: 500,
                threads,
            };
            let started = std::time::Instant::now();
            let report = gaitscope::eval::evaluate(&opts)?;
            let secs = started.elapsed().as_secs_f64();
            let steps: usize = report.episodes.iter().map(|e| e.steps).sum();
            println!(
                "{} episodes ({steps} env steps) in {secs:.1} s on {threads} thread{}: {:.1} episodes/s, {:.0} env steps/s",
                report.episodes.len(),
                if threads == 1 { "" } else { "s" },
                report.episodes.len() as f64 / secs,
                steps as f64 / secs
            );
            Ok(())
        }
        BenchCommand::Search {
            checkpoint,
            evaluations,
            episodes,
            threads,
        } => {
            use gaitscope::search;
            let label = gaitscope::eval::model_label(&checkpoint);
            let evaluator =
                search::PolicyEvaluator::new(&[(label.clone(), checkpoint.clone())], 500, threads)?;
            let world = evaluator.world();
            let opts = search::SearchOptions {
                models: vec![search::ModelId {
                    label,
                    path: checkpoint.display().to_string(),
                    model_crc32: gaitscope::policy::checkpoint::read_meta(&checkpoint)?.model_crc32,
                }],
                objective: search::Objective::Break,
                method: search::Method::Cma,
                reference: false,
                severity_budget: 1.0,
                unit: search::Unit::Joint,
                concentrate: false,
                latest_onset: 100,
                pushes: None,
                evaluations,
                episodes,
                held_out_episodes: episodes,
                held_out_seed_base: gaitscope::eval::EVAL_SEED_BASE,
                top: 1,
                shrink_evaluations: 0,
                shrink_slack: 0,
                max_steps: 500,
                goal_distance: world.env.goal[0].hypot(world.env.goal[1]),
                seed: 0,
                world: world.world.to_string(),
                version: env!("CARGO_PKG_VERSION").to_string(),
            };
            let scratch =
                std::env::temp_dir().join(format!("gaitscope-bench-search-{}", std::process::id()));
            let started = std::time::Instant::now();
            let report = search::run(&opts, &evaluator, &scratch);
            let secs = started.elapsed().as_secs_f64();
            let _ = std::fs::remove_dir_all(&scratch);
            let report = report?;
            let all: Vec<&search::Candidate> = report
                .searched
                .iter()
                .chain(report.top.iter().map(|c| &c.held_out))
                .collect();
            let episodes: usize = all.iter().map(|c| c.outcomes[0].len()).sum();
            let steps: usize = all
                .iter()
                .flat_map(|c| &c.outcomes[0])
                .map(|e| e.steps)
                .sum();
            println!(
                "{} candidates ({episodes} episodes, {steps} env steps) in {secs:.1} s on {threads} \
                 thread{}: {:.2} candidates/s, {:.1} episodes/s, {:.0} env steps/s",
                all.len(),
                if threads == 1 { "" } else { "s" },
                all.len() as f64 / secs,
                episodes as f64 / secs,
                steps as f64 / secs
            );
            Ok(())
        }
        BenchCommand::Train {
            steps,
            encoders,
            update,
            threads,
            json,
        } => {
            if steps == 0 || threads == 0 {
                bail!("--steps and --threads must be at least 1");
            }
            let scratch =
                std::env::temp_dir().join(format!("gaitscope-bench-{}", std::process::id()));
            let rows = gaitscope::bench::bench_train(
                &encoders.into_iter().map(Into::into).collect::<Vec<_>>(),
                steps,
                update.into(),
                threads,
                &scratch,
            )?;
            let _ = std::fs::remove_dir_all(&scratch);
            if json {
                for r in &rows {
                    println!("{}", serde_json::to_string(r)?);
                }
                return Ok(());
            }
            println!("encoder     train steps/s  updates/s (no env)  act/s (batch 1)");
            for r in rows {
                println!(
                    "{:<11} {:>13.1}  {:>18.1}  {:>15.0}",
                    r.encoder.name(),
                    r.train_steps_per_s,
                    r.updates_per_s,
                    r.act_per_s
                );
            }
            Ok(())
        }
    }
}
