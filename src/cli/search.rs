//! `gaitscope search`.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

use super::values::{MethodArg, UnitArg};
use gaitscope::search::{self, ModelId, Objective, PolicyEvaluator, SearchOptions};

#[derive(Args)]
pub(crate) struct SearchArgs {
    /// The checkpoint whose failures are searched for.
    #[arg(long, value_name = "DIR")]
    checkpoint: PathBuf,
    /// A second checkpoint: search for damage under which --checkpoint fails and this one
    /// succeeds (success(B) − success(A) on the same seeds); --reverse for the other way round.
    #[arg(long, value_name = "DIR")]
    against: Option<PathBuf>,
    /// With --against: damage under which --against fails and --checkpoint succeeds.
    #[arg(long, requires = "against")]
    reverse: bool,
    /// Severity budget K: Σ over joints of (1 − scale) ≤ K (1 = one joint dead, or two at 0.5).
    #[arg(long, default_value_t = 1.0, value_name = "K")]
    budget: f64,
    /// Candidates the optimiser evaluates (and the random reference as many).
    #[arg(long, default_value_t = 200)]
    evaluations: usize,
    #[arg(long, value_enum, default_value_t = MethodArg::Cma)]
    method: MethodArg,
    /// Skip the random-search reference at the same budget.
    #[arg(long)]
    no_reference: bool,
    /// Search seeds: episodes per candidate, the same seeds for every candidate.
    #[arg(long, default_value_t = 16)]
    episodes: usize,
    /// Held-out episodes for each top candidate (eval's seeds: `eval --scenario` repeats them).
    #[arg(long, default_value_t = 100)]
    held_out: usize,
    /// First held-out seed (as eval's --seed).
    #[arg(long, default_value_t = gaitscope::eval::EVAL_SEED_BASE)]
    held_out_seed: u64,
    /// Distinct top candidates re-run on the held-out seeds.
    #[arg(long, default_value_t = 3)]
    top: usize,
    /// Evaluations the shrinker may spend reducing the best schedule.
    #[arg(long, default_value_t = 100)]
    shrink_evaluations: usize,
    /// Search-seed episodes whose failure a shrinking step may give back (default 0: none).
    /// On chaotic walks a 1 % nudge to a joint flips an outcome or two; 1 lets the shrinker
    /// drop such nudges instead of keeping them as damage.
    #[arg(long, default_value_t = 0)]
    shrink_slack: usize,
    /// Search one push per schedule as well — a horizontal force on the torso or a leg, up to
    /// 1,000 N for up to 10 env steps — with at most this impulse (newton-seconds; the Ant
    /// weighs about 9 N). Off unless given.
    #[arg(long, value_name = "N·S")]
    push_impulse: Option<f64>,
    /// What one damage gene acts on: each joint its own scale and onset, or each leg one for
    /// both its joints (as legs die in the dead-legs world; a dead leg costs 2 of the budget).
    #[arg(long, value_enum, default_value_t = UnitArg::Joint)]
    unit: UnitArg,
    /// Over the budget, keep the largest damages whole and cut the rest, instead of scaling
    /// every damage down together: concentrated damage, so dead joints and legs are reachable.
    #[arg(long)]
    concentrate: bool,
    /// The latest step a joint's damage (or the push) may start at.
    #[arg(long, default_value_t = 100)]
    latest_onset: usize,
    /// Episodes end after this many steps (default: the models' world's limit — 500 in the
    /// paper's world, dead-legs 1000, dead-legs-short 400).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
    /// The optimiser's seed (and which search seeds the episodes use).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Worker threads (default: all cores); results do not depend on it.
    #[arg(long)]
    threads: Option<usize>,
    /// Output folder (default
    /// search/MODEL[-vs-OTHER]-kK[-legs][-concentrated][-pushI]-METHOD-sSEED); an existing
    /// one of the same search resumes.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

pub(crate) fn search_command(args: SearchArgs) -> Result<()> {
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let mut dirs = vec![args.checkpoint.clone()];
    dirs.extend(args.against.clone());
    if args.reverse {
        dirs.reverse();
    }
    let mut models = Vec::new();
    let mut worlds = Vec::new();
    for dir in &dirs {
        let meta = gaitscope::policy::checkpoint::read_meta(dir)?;
        let mut label = gaitscope::eval::model_label(dir);
        if models.iter().any(|m: &ModelId| m.label == label) {
            label.push('\'');
        }
        models.push(ModelId {
            label,
            path: dir.display().to_string(),
            model_crc32: meta.model_crc32,
        });
        worlds.push(meta.env);
    }
    let max_steps = super::step_limit_of(
        args.max_steps,
        models.iter().map(|m| m.label.as_str()).zip(&worlds),
        &gaitscope::GaitConfig::default(),
    )?;
    let evaluator = PolicyEvaluator::new(
        &models
            .iter()
            .zip(&dirs)
            .map(|(m, d)| (m.label.clone(), d.clone()))
            .collect::<Vec<_>>(),
        max_steps,
        threads,
    )?;
    let world = evaluator.world();
    let method: search::Method = args.method.into();
    let opts = SearchOptions {
        objective: if args.against.is_some() {
            Objective::Separate
        } else {
            Objective::Break
        },
        method,
        reference: !args.no_reference,
        severity_budget: args.budget,
        unit: args.unit.into(),
        concentrate: args.concentrate,
        latest_onset: args.latest_onset,
        pushes: args.push_impulse.map(|impulse| search::space::PushSpace {
            impulse,
            step_seconds: evaluator.step_seconds(),
        }),
        evaluations: args.evaluations,
        episodes: args.episodes,
        held_out_episodes: args.held_out,
        held_out_seed_base: args.held_out_seed,
        top: args.top,
        shrink_evaluations: args.shrink_evaluations,
        shrink_slack: args.shrink_slack,
        max_steps,
        goal_distance: world.env.goal[0].hypot(world.env.goal[1]),
        seed: args.seed,
        world: world.world.to_string(),
        version: env!("CARGO_PKG_VERSION").to_string(),
        models,
    };
    opts.check()?;
    let out = args.out.unwrap_or_else(|| {
        let vs = opts
            .models
            .get(1)
            .map(|m| format!("-vs-{}", m.label))
            .unwrap_or_default();
        let push = opts
            .pushes
            .map(|p| format!("-push{}", p.impulse))
            .unwrap_or_default();
        let legs = if opts.unit.is_joint() { "" } else { "-legs" };
        let concentrated = if opts.concentrate {
            "-concentrated"
        } else {
            ""
        };
        PathBuf::from("search").join(format!(
            "{}{vs}-k{}{legs}{concentrated}{push}-{}-s{}",
            opts.models[0].label,
            opts.severity_budget,
            method.name(),
            opts.seed
        ))
    });
    let started = std::time::Instant::now();
    let report = search::run(&opts, &evaluator, &out)?;
    let secs = started.elapsed().as_secs_f64();
    println!(
        "{}",
        gaitscope::files::read_text_capped(&out.join("summary.md"), 1 << 20)?
    );
    let evaluated = report.searched.len() + report.reference.len();
    eprintln!(
        "{evaluated} search candidates (and {} more held-out and shrink runs) in {secs:.0} s, {threads} thread{}",
        report.top.len() + report.shrunk.evaluations + 1 + report.reference_best.is_some() as usize,
        if threads == 1 { "" } else { "s" }
    );
    for path in &report.written {
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}
