//! The command line's names for the library's choices. The library's enums know nothing of clap
//! (issue 50: CLI types at the edge); each flag's value type here mirrors one of them, with the
//! help text `--help` shows, and converts both ways by exhaustive matches (a library variant the flag does not offer is named as such), so a variant added on
//! either side without the other is a compile error.

use gaitscope::explain::Target;
use gaitscope::policy::sb3::ImportEncoder;
use gaitscope::policy::{AuxKind, EncoderKind, Privileged};
use gaitscope::rollout::BuiltinPolicy;
use gaitscope::search::{Method, Unit};
use gaitscope::train::sac::UpdatePath;
#[cfg(feature = "video")]
use gaitscope::video::CameraMode;

macro_rules! mirror {
    ($(#[$meta:meta])* $cli:ident => $lib:ident {
        $($(#[$doc:meta])* $variant:ident),+ $(,)?
    }) => {
        mirror!($(#[$meta])* $cli => $lib, not offered: [] { $($(#[$doc])* $variant),+ });
    };
    // `not offered`: library variants with no flag value (e.g. an oracle's `none`, which is the
    // flag left out); every other library variant must have one.
    ($(#[$meta:meta])* $cli:ident => $lib:ident, not offered: [$($hidden:ident),*] {
        $($(#[$doc:meta])* $variant:ident),+ $(,)?
    }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        pub(crate) enum $cli {
            $($(#[$doc])* $variant),+
        }

        impl From<$cli> for $lib {
            fn from(value: $cli) -> Self {
                match value {
                    $($cli::$variant => $lib::$variant),+
                }
            }
        }

        impl TryFrom<$lib> for $cli {
            /// The library's variant that has no flag value.
            type Error = $lib;

            fn try_from(value: $lib) -> Result<Self, $lib> {
                match value {
                    $($lib::$variant => Ok($cli::$variant),)+
                    $($lib::$hidden => Err(value),)*
                }
            }
        }
    };
}

mirror! {
    /// `--encoder`: which feature extractor a model uses.
    EncoderArg => EncoderKind {
        /// Memoryless baseline: the observation only.
        None,
        /// The paper's context encoder.
        Lstm,
        /// The ablation: an MLP over the flattened window.
        MlpWindow,
    }
}

mirror! {
    /// `--aux`: the auxiliary loss.
    AuxArg => AuxKind {
        /// None: plain SAC.
        None,
        /// Predict the normalised change of the observation from [z, o_t, a_t].
        Dynamics,
    }
}

mirror! {
    /// `--privileged`: an oracle's extra inputs.
    PrivilegedArg => Privileged, not offered: [None] {
        /// The true per-joint torque scales (8 values).
        Damage,
        /// The torque each joint lost, 1 − scale (8 values, 0 while whole).
        TorqueLost,
    }
}

mirror! {
    /// `--update`: how a gradient update is computed.
    UpdateArg => UpdatePath {
        /// Hand-written forward and backward passes over preallocated buffers.
        Fused,
        /// candle's autograd, op by op: the reference the fused path is tested against.
        Reference,
    }
}

mirror! {
    /// `--policy`: policies that need no checkpoint.
    BuiltinArg => BuiltinPolicy {
        /// Uniform in [−1, 1]⁸ from a seeded RNG.
        Random,
        /// All zeros: the Ant stands still.
        Zero,
    }
}

mirror! {
    /// `import --encoder`: the encoder an imported model gets.
    ImportEncoderArg => ImportEncoder {
        /// `none` for a 29-d observation, `lstm` for the 621-d folded window with one LSTM.
        Auto,
        None,
        Lstm,
    }
}

#[cfg(feature = "video")]
mirror! {
    /// `video --camera`: how the camera moves.
    CameraArg => CameraMode {
        /// Follows the torso at 5 m, as the viewer's 3-D view does.
        Track,
        /// Still, framing the start and the goal.
        Fixed,
    }
}

mirror! {
    /// `explain --target`: what is explained.
    TargetArg => Target {
        /// Each dimension of the encoder's latent z (the window alone decides it).
        Z,
        /// Each dimension of the deterministic action tanh(μ) (window and current observation).
        Action,
    }
}

mirror! {
    /// `search --method`: how candidates are proposed.
    MethodArg => Method {
        /// CMA-ES (the `cmaes` crate): a Gaussian that moves toward the best candidates.
        Cma,
        /// Uniform in the space (the reference every search is compared with).
        Random,
    }
}

mirror! {
    /// `search --unit`: what one damage gene acts on.
    UnitArg => Unit {
        /// Each joint its own scale and onset.
        Joint,
        /// Each leg one scale and onset for both its joints (a dead leg costs 2 of the budget).
        Leg,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::ValueEnum;

    fn names<T: ValueEnum>() -> Vec<String> {
        T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value())
            .map(|p| p.get_name().to_string())
            .collect()
    }

    /// The names on the command line are the ones the docs, scripts and sweeps use, and each
    /// converts to the library's variant of the same name.
    #[test]
    fn flag_values_keep_their_names() {
        assert_eq!(names::<EncoderArg>(), ["none", "lstm", "mlp-window"]);
        assert_eq!(names::<AuxArg>(), ["none", "dynamics"]);
        assert_eq!(names::<PrivilegedArg>(), ["damage", "torque-lost"]);
        assert_eq!(names::<UpdateArg>(), ["fused", "reference"]);
        assert_eq!(names::<BuiltinArg>(), ["random", "zero"]);
        assert_eq!(names::<ImportEncoderArg>(), ["auto", "none", "lstm"]);
        assert_eq!(names::<TargetArg>(), ["z", "action"]);
        assert_eq!(names::<UnitArg>(), ["joint", "leg"]);
        assert_eq!(
            EncoderKind::from(EncoderArg::MlpWindow),
            EncoderKind::MlpWindow
        );
        assert_eq!(
            EncoderArg::try_from(EncoderKind::Lstm),
            Ok(EncoderArg::Lstm)
        );
        assert_eq!(
            PrivilegedArg::try_from(Privileged::None),
            Err(Privileged::None)
        );
        assert_eq!(
            ImportEncoder::from(ImportEncoderArg::None),
            ImportEncoder::None
        );
        #[cfg(feature = "video")]
        {
            assert_eq!(names::<CameraArg>(), ["track", "fixed"]);
            assert_eq!(CameraMode::from(CameraArg::Fixed), CameraMode::Fixed);
        }
    }
}
