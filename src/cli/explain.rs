//! `gaitscope explain`.

use anyhow::Result;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;

use gaitscope::explain::{Target, explain_step};

use super::values::TargetArg;
use gaitscope::{Condition, ConditionChoice};

use super::EnvArgs;

#[derive(Args)]
pub(crate) struct ExplainArgs {
    /// Checkpoint whose decision is explained.
    #[arg(long, value_name = "DIR")]
    checkpoint: PathBuf,
    /// The step whose decision is explained (after this many steps of the episode).
    #[arg(long)]
    step: usize,
    /// z (each latent dimension; encoder models) or action (each action dimension).
    #[arg(long, value_enum, default_value_t = TargetArg::Z)]
    target: TargetArg,
    /// Damage condition; without it the episode draws one from its seed.
    #[arg(long, value_name = "healthy|mild|severe")]
    condition: Option<Condition>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Interpolation points of the path integral (default: from 64, doubled until the
    /// attributions add up to the output's change within 1 % or 1e-3).
    #[arg(long)]
    ig_steps: Option<usize>,
    /// One JSON object (attribution: output dims × window steps × features) instead of the
    /// summary.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    env: EnvArgs,
}

pub(crate) fn explain_command(args: ExplainArgs) -> Result<()> {
    let mut requested = args.env.load()?;
    if let Some(c) = args.condition {
        requested.damage.condition = ConditionChoice::Fixed(c);
    }
    requested.env.max_episode_steps = requested.env.max_episode_steps.max(args.step + 1);
    let actor = gaitscope::lane::Actor::load(&args.checkpoint)?;
    args.env.note_unused(&actor, &requested);
    let explained = explain_step(
        &actor,
        &requested,
        args.seed,
        args.step,
        Target::from(args.target),
        args.ig_steps,
    )?;
    let (a, groups) = (&explained.attribution, &explained.groups);
    let per_slot = a.per_slot();
    let per_group = a.per_group(groups);
    if args.json {
        let out = json!({
            "step": args.step,
            "target": a.target,
            "ig_steps": a.steps,
            "complete": a.is_complete(),
            "attribution": a.attribution,
            "obs_attribution": a.obs_attribution,
            "output": a.output,
            "baseline_output": a.baseline_output,
            "completeness_error": a.completeness_error(),
            "window_filled": explained.window_filled,
            "window_len": explained.window_len,
            "condition": explained.condition.name(),
            "torque": explained.torque.iter().map(|(j, t)| json!({"joint": j, "torque": t})).collect::<Vec<_>>(),
            "damage_onset": explained.damage_onset,
            "summary": {
                "per_slot": per_slot,
                "per_group": per_group.iter().map(|(n, v)| json!({"group": n, "abs_attribution": v})).collect::<Vec<_>>(),
                "groups": groups,
            },
        });
        println!("{out}");
        return Ok(());
    }
    if !a.is_complete() {
        eprintln!(
            "warning: with {} interpolation points the attributions do not add up to the output's change (within 1 % or 1e-3); try more --ig-steps",
            a.steps
        );
    }
    println!(
        "{} at step {} (seed {}, {} interpolation points): {} output dims, completeness error at most {:.2e}",
        match Target::from(args.target) {
            Target::Z => "z",
            Target::Action => "action",
        },
        args.step,
        args.seed,
        a.steps,
        a.output.len(),
        a.completeness_error().iter().fold(0f64, |m, &e| m.max(e))
    );
    // The damage at this decision, in the views' words.
    let lost: Vec<String> = explained
        .torque
        .iter()
        .filter(|(_, t)| t != "full torque")
        .map(|(j, t)| format!("{j} {t}"))
        .collect();
    println!(
        "condition {}; at this step {}{}",
        explained.condition,
        if lost.is_empty() {
            "every joint has full torque".to_string()
        } else {
            lost.join(", ")
        },
        explained
            .damage_onset
            .map_or(String::new(), |s| format!(" (damage since step {s})"))
    );
    let unit = match Target::from(args.target) {
        Target::Z => "in units of z, summed over its dims",
        Target::Action => "in units of the action command (−1 … 1), summed over its dims",
    };
    if explained.window_filled == 0 && !per_slot.is_empty() {
        println!(
            "\nthe window is empty at step {} (a reset zero-pads all {} slots, the integration's \
             baseline itself): there is nothing in it to attribute, so every slot is 0",
            args.step, explained.window_len
        );
    }
    if !per_slot.is_empty() && explained.window_filled > 0 {
        println!(
            "\nper window slot ({unit}; oldest first, slot {} the latest step; {} of {} slots \
             hold steps, the rest are the reset's zeros):",
            per_slot.len() - 1,
            explained.window_filled,
            explained.window_len
        );
        for (t, v) in per_slot.iter().enumerate() {
            println!("  {t:>2}  {v:+.4}");
        }
    }
    if let Some(obs) = &a.obs_attribution {
        let total: f64 = obs.iter().flatten().map(|v| v.abs()).sum();
        println!("\ncurrent observation: |attribution| {total:.4} in all ({unit})");
    }
    if per_slot.is_empty() || explained.window_filled == 0 {
        return Ok(());
    }
    println!("\nper window feature group (|attribution| {unit}, all slots):");
    let mut sorted = per_group;
    sorted.sort_by(|a, b| b.1.total_cmp(&a.1));
    for (name, v) in sorted {
        println!("  {name:<8} {v:.4}");
    }
    Ok(())
}
