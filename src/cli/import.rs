//! `gaitscope import-sb3`.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

use gaitscope::policy::sb3;

use super::values::ImportEncoderArg;

#[derive(Args)]
pub(crate) struct ImportSb3Args {
    /// The SB3 archive, as `model.save()` wrote it.
    model: PathBuf,
    /// The checkpoint folder to create (must not exist).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// The encoder: auto picks none for a 29-d observation, lstm for the 621-d folded window.
    #[arg(long, value_enum, default_value_t = ImportEncoderArg::Auto)]
    encoder: ImportEncoderArg,
}

pub(crate) fn import_sb3_command(args: ImportSb3Args) -> Result<()> {
    let summary = sb3::import_sb3(&args.model, &args.out, args.encoder.into())?;
    let net = &summary.net;
    println!(
        "imported {} (Stable-Baselines3 {}, {} steps) → {}",
        summary.provenance.file,
        summary.provenance.version,
        summary.num_timesteps,
        args.out.display()
    );
    println!(
        "  encoder {}{}, hidden {:?}, z {}, α {:.4}, {} tensors, sha256 {}",
        net.encoder,
        if net.share_encoder { " (shared)" } else { "" },
        net.hidden,
        net.z_dim,
        summary.alpha,
        summary.tensors,
        &summary.provenance.sha256[..12]
    );
    Ok(())
}
