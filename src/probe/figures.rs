//! The probe figures: PCA scatter of z, latent shift and progress aligned to damage onset,
//! fatigue per joint.

use std::path::{Path, PathBuf};

use crate::damage::{Condition, N_ACTUATORS};
use crate::plots::{self, BandSeries, ErrorBarSeries};

use super::{ProbeError, ProbeFile, ProbeStep};

/// Steps aligned to each episode's first trigger: (offset, value) for offsets in `range`.
fn aligned(
    steps: &[ProbeStep],
    range: std::ops::RangeInclusive<i64>,
    value: impl Fn(&ProbeStep, &[&ProbeStep]) -> f64,
) -> Vec<Vec<f64>> {
    let mut by_episode: std::collections::BTreeMap<usize, Vec<&ProbeStep>> = Default::default();
    for s in steps {
        by_episode.entry(s.episode).or_default().push(s);
    }
    let width = (range.end() - range.start() + 1) as usize;
    let mut curves = Vec::new();
    for episode in by_episode.values() {
        let Some(onset) = episode.last().and_then(|s| s.first_trigger) else {
            continue;
        };
        if episode[0].condition == Condition::Healthy {
            continue; // a trigger changes nothing under the healthy condition
        }
        let mut curve = vec![f64::NAN; width];
        for s in episode {
            let offset = s.t as i64 - onset as i64;
            if range.contains(&offset) {
                curve[(offset - range.start()) as usize] = value(s, episode);
            }
        }
        curves.push(curve);
    }
    curves
}

/// Mean and ±1 standard deviation over curves, ignoring missing points.
fn band(label: &str, colour: usize, xs: &[f64], curves: &[Vec<f64>]) -> BandSeries {
    let (mut mean, mut low, mut high) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..xs.len() {
        let v: Vec<f64> = curves
            .iter()
            .map(|c| c[k])
            .filter(|v| v.is_finite())
            .collect();
        let m = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt();
        mean.push(m);
        low.push(m - sd);
        high.push(m + sd);
    }
    BandSeries {
        label: format!("{label} (n = {})", curves.len()),
        colour,
        dashed: false,
        x: xs.to_vec(),
        mean,
        low,
        high,
    }
}

/// The figures of the run `model` (its folder's name): PCA scatter, onset alignment, fatigue
/// asymmetry.
pub fn figures(
    file: &ProbeFile,
    model: &str,
    encoder: &[ProbeStep],
    baseline: Option<&[ProbeStep]>,
    out: &Path,
) -> Result<Vec<PathBuf>, ProbeError> {
    std::fs::create_dir_all(out).map_err(|e| ProbeError::Read {
        path: out.to_owned(),
        reason: e.into(),
    })?;
    let mut written = Vec::new();
    // This model's colour and the baseline's, as in every other figure.
    let colours = plots::colour_slots(
        &[&crate::eval::seeds::group_of(model), "baseline"],
        &plots::MODEL_COLOURS,
    );

    // PCA of z, coloured by number of damaged joints.
    let mut classes: Vec<(String, Vec<(f64, f64)>)> = (0..=N_ACTUATORS)
        .map(|n| (format!("{n} damaged"), Vec::new()))
        .collect();
    for s in encoder {
        let p = file
            .pca
            .project(&s.z.iter().map(|&v| v as f64).collect::<Vec<_>>());
        classes[s.damaged.iter().filter(|&&d| d).count()]
            .1
            .push((p[0], p.get(1).copied().unwrap_or(0.0)));
    }
    classes.retain(|(_, p)| !p.is_empty());
    let ev = &file.pca.explained_variance_ratio;
    let path = out.join("pca_z.png");
    plots::scatter(
        &path,
        "PCA of z, coloured by number of damaged joints",
        (
            &format!("PC1 ({:.0} %)", 100.0 * ev.first().unwrap_or(&0.0)),
            &format!("PC2 ({:.0} %)", 100.0 * ev.get(1).unwrap_or(&0.0)),
        ),
        &classes,
    )?;
    written.push(path);

    // Onset: latent shift and progress rate around the first trigger.
    let range = -20i64..=60;
    let xs: Vec<f64> = range.clone().map(|v| v as f64).collect();
    let shift = aligned(encoder, range.clone(), |s, episode| {
        let onset = episode.last().and_then(|e| e.first_trigger).unwrap_or(0);
        let pre: Vec<&&ProbeStep> = episode.iter().filter(|e| e.t < onset).collect();
        let dim = s.z.len();
        let mean: Vec<f64> = (0..dim)
            .map(|j| pre.iter().map(|e| e.z[j] as f64).sum::<f64>() / pre.len().max(1) as f64)
            .collect();
        s.z.iter()
            .zip(&mean)
            .map(|(&v, m)| (v as f64 - m).powi(2))
            .sum::<f64>()
            .sqrt()
    });
    let path = out.join("onset_latent_shift.png");
    plots::bands(
        &path,
        // Spelled out: plotters draws the combining macron of "z̄" as a separate glyph.
        "Latent shift at damage onset: distance of z from its pre-onset mean",
        "steps since first trigger",
        "‖z − mean z before onset‖",
        &[band(model, colours[0], &xs, &shift)],
        Some(0.0),
        plots::SeriesLabelPosition::UpperLeft,
    )?;
    written.push(path);
    let dt = 0.05;
    let mut progress = vec![band(
        model,
        colours[0],
        &xs,
        &aligned(encoder, range.clone(), |s, _| s.progress / dt),
    )];
    if let Some(base) = baseline {
        progress.push(band(
            "baseline",
            colours[1],
            &xs,
            &aligned(base, range.clone(), |s, _| s.progress / dt),
        ));
    }
    let path = out.join("onset_progress.png");
    plots::bands(
        &path,
        "Goal-progress rate at damage onset",
        "steps since first trigger",
        "progress (m/s)",
        &progress,
        Some(0.0),
        plots::SeriesLabelPosition::LowerRight,
    )?;
    written.push(path);

    // Fatigue asymmetry: one episode's fatigue per joint, and mean first-trigger step per joint.
    if let Some(first) = encoder.first() {
        let ep: Vec<&ProbeStep> = encoder
            .iter()
            .filter(|s| s.episode == first.episode)
            .collect();
        let series: Vec<BandSeries> = (0..N_ACTUATORS)
            .map(|i| {
                let y: Vec<f64> = ep.iter().map(|s| s.fatigue[i]).collect();
                BandSeries {
                    label: file.joint_names[i].clone(),
                    // Actuators come in (hip, ankle) pairs per leg: a colour per leg, the
                    // ankle dashed, so eight lines read apart with six colours.
                    colour: i / 2,
                    dashed: file.joint_names[i].starts_with("ankle"),
                    x: ep.iter().map(|s| s.t as f64).collect(),
                    mean: y.clone(),
                    low: y.clone(),
                    high: y,
                }
            })
            .collect();
        let path = out.join("fatigue_episode.png");
        plots::bands(
            &path,
            &format!("Fatigue per joint over one episode ({})", first.condition),
            "step",
            "fatigue",
            &series,
            None,
            // Fatigue only grows: the start of the episode stays clear.
            plots::SeriesLabelPosition::UpperLeft,
        )?;
        written.push(path);
    }
    // The last step of each episode holds its complete trigger record.
    let mut last_of_episode: std::collections::BTreeMap<usize, &ProbeStep> = Default::default();
    for s in encoder {
        last_of_episode.insert(s.episode, s);
    }
    let trigger_steps: Vec<Vec<f64>> = (0..N_ACTUATORS)
        .map(|i| {
            last_of_episode
                .values()
                .filter_map(|s| s.joint_triggers[i].map(|t| t as f64))
                .collect()
        })
        .collect();
    let order: Vec<usize> = {
        let mut o: Vec<usize> = (0..N_ACTUATORS).collect();
        o.sort_by_key(|&i| {
            (
                !file.joint_names[i].starts_with("hip"),
                file.joint_names[i].clone(),
            )
        });
        o
    };
    let names: Vec<&str> = order
        .iter()
        .map(|&i| file.joint_names[i].as_str())
        .collect();
    let points: Vec<(f64, f64, f64)> = order
        .iter()
        .map(|&i| {
            let v = &trigger_steps[i];
            let n = v.len().max(1) as f64;
            let m = v.iter().sum::<f64>() / n;
            let se = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n).sqrt() / n.sqrt();
            (m, m - 1.96 * se, m + 1.96 * se)
        })
        .collect();
    let max = points
        .iter()
        .map(|p| p.2)
        .filter(|v| v.is_finite())
        .fold(10.0f64, f64::max);
    let path = out.join("trigger_step_by_joint.png");
    plots::error_bars(
        &path,
        "Mean first-trigger step per joint (hips vs ankles)",
        "step",
        &names,
        &[ErrorBarSeries {
            label: model.to_string(),
            colour: colours[0],
            in_legend: true,
            dots: Vec::new(),
            points,
        }],
        (0.0, max * 1.05),
    )?;
    written.push(path);
    Ok(written)
}
