//! Colours that mean something, one set for every view (the Rerun stream, the egui panel, the
//! web page, the video's labels): a joint's colour is the torque it has actually lost, and each
//! model (lane) keeps one hue in every view, its trail and its lines.

use crate::damage::JointState;

/// What a joint's torque is now, as every view names and colours it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Torque {
    /// Scale 1: nothing lost, whatever fatigue says (a trigger under the healthy condition
    /// keeps scale 1 and stays this colour).
    Full,
    /// 0 < scale < 1, by fatigue or a scenario.
    Reduced(f64),
    /// No torque left (scale 0), or killed by the world's dead-actuator draw.
    Dead,
    /// Scale pinned by a person (the panel, the page, a fork's `scale:`).
    Pinned(f64),
}

/// Full torque: green.
pub const FULL: [u8; 3] = [70, 170, 90];
/// A little lost (scale just under 1): amber; more lost shades to [`REDUCED_MOST`].
pub const REDUCED_LEAST: [u8; 3] = [235, 190, 50];
/// Almost all lost (scale just over 0): red.
pub const REDUCED_MOST: [u8; 3] = [215, 35, 35];
/// Dead: dark slate, its own colour (not the end of the red ramp).
pub const DEAD: [u8; 3] = [55, 60, 75];
/// Pinned by hand: violet.
pub const PINNED: [u8; 3] = [150, 80, 210];

impl Torque {
    pub fn of(scale: f64, state: JointState) -> Self {
        match state {
            JointState::Manual => Torque::Pinned(scale),
            JointState::Dead => Torque::Dead,
            _ if scale <= 0.0 => Torque::Dead,
            _ if scale >= 1.0 => Torque::Full,
            _ => Torque::Reduced(scale),
        }
    }

    pub fn rgb(self) -> [u8; 3] {
        match self {
            Torque::Full => FULL,
            Torque::Dead => DEAD,
            Torque::Pinned(_) => PINNED,
            Torque::Reduced(scale) => {
                // Lost fraction in (0, 1): amber at a sliver lost, red at nearly all.
                let lost = (1.0 - scale).clamp(0.0, 1.0);
                std::array::from_fn(|i| {
                    let (a, b) = (REDUCED_LEAST[i] as f64, REDUCED_MOST[i] as f64);
                    (a + (b - a) * lost).round() as u8
                })
            }
        }
    }

    pub fn rgba(self) -> [u8; 4] {
        let [r, g, b] = self.rgb();
        [r, g, b, 255]
    }

    /// The words the views use: "full torque", "scale 0.10", "dead", "pinned 0.40 (manual)".
    pub fn describe(self) -> String {
        match self {
            Torque::Full => "full torque".into(),
            Torque::Reduced(s) => format!("scale {s:.2}"),
            Torque::Dead => "dead".into(),
            Torque::Pinned(s) => format!("pinned {s:.2} (manual)"),
        }
    }

    /// Whether torque is lost (anything but full; a pin at 1 loses none).
    pub fn lost(self) -> bool {
        match self {
            Torque::Full => false,
            Torque::Pinned(s) => s < 1.0,
            Torque::Reduced(_) | Torque::Dead => true,
        }
    }
}

/// The key every view shows for [`Torque`], in order: (name, colour).
pub fn torque_key() -> [(&'static str, [u8; 3]); 5] {
    [
        ("full torque", FULL),
        ("scale 0.9", Torque::Reduced(0.9).rgb()),
        ("scale 0.1", Torque::Reduced(0.1).rgb()),
        ("dead (0)", DEAD),
        ("pinned by hand", PINNED),
    ]
}

/// Each model's hue in degrees, by lane (the first model, the second, a fork …): orange, blue,
/// teal, magenta, olive, then around again — far apart from each other and, drawn as lines and
/// trails, never on the legs, whose colours are the torque key's.
pub const MODEL_HUES: [f64; 5] = [24.0, 212.0, 175.0, 320.0, 60.0];

/// The names every view gives the model hues, in [`MODEL_HUES`]' order.
pub const MODEL_HUE_NAMES: [&str; 5] = ["orange", "blue", "teal", "magenta", "olive"];

/// Lane `index`'s colour: its trail, its one-line series (goal distance), its key entry.
pub fn model(index: usize) -> [u8; 3] {
    model_shade(index, 0, 1)
}

/// The name of lane `index`'s hue ("orange").
pub fn model_hue_name(index: usize) -> &'static str {
    MODEL_HUE_NAMES[index % MODEL_HUE_NAMES.len()]
}

/// The `i`-th of `n` shades of lane `index`'s hue: one hue, lightness from dark to light, so a
/// lane's lines read as one colour and its joints within it still differ.
pub fn model_shade(index: usize, i: usize, n: usize) -> [u8; 3] {
    let hue = MODEL_HUES[index % MODEL_HUES.len()];
    let light = if n <= 1 {
        0.45
    } else {
        0.28 + 0.42 * i as f64 / (n - 1) as f64
    };
    hsl_to_rgb(hue, 0.8, light)
}

/// HSL (hue in degrees, saturation and lightness in 0..=1) to 8-bit RGB.
pub fn hsl_to_rgb(hue: f64, sat: f64, light: f64) -> [u8; 3] {
    let c = (1.0 - (2.0 * light - 1.0).abs()) * sat;
    let h = hue.rem_euclid(360.0) / 60.0;
    let x = c * (1.0 - (h % 2.0 - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = light - c / 2.0;
    let to8 = |v: f64| ((v + m) * 255.0).round().clamp(0.0, 255.0) as u8;
    [to8(r), to8(g), to8(b)]
}

/// A signed contribution on a diverging scale: white at 0, red as it raises the quantity, blue
/// as it lowers it, full colour at `max_abs` (the largest magnitude shown beside it).
pub fn diverging(value: f64, max_abs: f64) -> [u8; 3] {
    const RED: [f64; 3] = [200.0, 40.0, 40.0];
    const BLUE: [f64; 3] = [40.0, 90.0, 200.0];
    let t = if max_abs > 0.0 && value.is_finite() {
        (value / max_abs).clamp(-1.0, 1.0)
    } else {
        0.0
    };
    let end = if t >= 0.0 { RED } else { BLUE };
    let mix = |c: f64| (255.0 + (c - 255.0) * t.abs()).round() as u8;
    [mix(end[0]), mix(end[1]), mix(end[2])]
}

/// A leg's state in the gait diagram while its foot is on the floor: its worst joint's torque,
/// as a category (the state view colours a fixed set of values).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LegTorque {
    Full,
    Reduced,
    Dead,
    Pinned,
}

impl LegTorque {
    pub const ALL: [LegTorque; 4] = [
        LegTorque::Full,
        LegTorque::Reduced,
        LegTorque::Dead,
        LegTorque::Pinned,
    ];

    /// The leg's category from its joints' torques: a dead joint outranks a weakened one, a
    /// weakened one a pin, a pin full torque.
    pub fn of(joints: impl IntoIterator<Item = Torque>) -> Self {
        let rank = |t: &Torque| match t {
            Torque::Dead => 3,
            Torque::Reduced(_) => 2,
            Torque::Pinned(_) => 1,
            Torque::Full => 0,
        };
        match joints.into_iter().max_by_key(rank) {
            Some(Torque::Dead) => LegTorque::Dead,
            Some(Torque::Reduced(_)) => LegTorque::Reduced,
            Some(Torque::Pinned(_)) => LegTorque::Pinned,
            _ => LegTorque::Full,
        }
    }

    /// The state's name in the gait view ("stance · full torque").
    pub const fn stance_name(self) -> &'static str {
        match self {
            LegTorque::Full => "stance · full torque",
            LegTorque::Reduced => "stance · torque lost",
            LegTorque::Dead => "stance · joint(s) dead",
            LegTorque::Pinned => "stance · pinned by hand",
        }
    }

    /// Its tint: the torque key's colour (a weakened leg at the ramp's middle, scale 0.5).
    pub fn rgb(self) -> [u8; 3] {
        match self {
            LegTorque::Full => FULL,
            LegTorque::Reduced => Torque::Reduced(0.5).rgb(),
            LegTorque::Dead => DEAD,
            LegTorque::Pinned => PINNED,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_diverging_scale_is_white_at_zero_and_saturates_at_the_largest() {
        assert_eq!(diverging(0.0, 2.0), [255, 255, 255]);
        assert_eq!(diverging(2.0, 2.0), [200, 40, 40]);
        assert_eq!(diverging(-5.0, 2.0), [40, 90, 200]);
        // Halfway to red: 255 + (200 − 255)/2 = 227.5 → 228, 255 − 107.5 = 147.5 → 148.
        assert_eq!(diverging(1.0, 2.0), [228, 148, 148]);
        assert_eq!(diverging(f64::NAN, 2.0), [255, 255, 255]);
        assert_eq!(diverging(1.0, 0.0), [255, 255, 255]);
    }

    #[test]
    fn colour_follows_the_torque_lost_not_the_trigger() {
        // A triggered joint at scale 1 (the paper's healthy condition) is full-torque green.
        assert_eq!(Torque::of(1.0, JointState::Triggered).rgb(), FULL);
        assert_eq!(Torque::of(1.0, JointState::Healthy).rgb(), FULL);
        // The ramp by lost torque, amber to red, by hand from the endpoints.
        assert_eq!(Torque::of(0.5, JointState::Triggered).rgb(), [225, 113, 43]);
        // A sliver lost is the amber end; the ramp darkens monotonically towards red.
        assert_eq!(
            Torque::of(1.0 - 1e-12, JointState::Triggered).rgb(),
            REDUCED_LEAST
        );
        let g = |s: f64| Torque::Reduced(s).rgb()[1];
        assert!(g(0.9) > g(0.5) && g(0.5) > g(0.1));
        // Dead and pinned have their own colours, off the ramp.
        assert_eq!(Torque::of(0.0, JointState::Triggered).rgb(), DEAD);
        assert_eq!(Torque::of(0.0, JointState::Dead).rgb(), DEAD);
        assert_eq!(Torque::of(0.0, JointState::Manual).rgb(), PINNED);
        assert_eq!(Torque::of(1.0, JointState::Manual).rgb(), PINNED);
        assert!(!Torque::of(1.0, JointState::Manual).lost());
        assert!(Torque::of(0.3, JointState::Healthy).lost());
        // Every key colour differs from every other, and the model hues from all of them.
        let mut all: Vec<[u8; 3]> = torque_key().iter().map(|(_, c)| *c).collect();
        all.extend((0..MODEL_HUES.len()).map(model));
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                assert_ne!(a, b);
            }
        }
    }

    #[test]
    fn model_hues_by_hand_and_shades_darken_to_lighten() {
        // Orange (24°) at lightness 0.45, saturation 0.8: c = 0.72, x = 0.288, m = 0.09,
        // so (0.81, 0.378, 0.09) × 255.
        assert_eq!(model(0), [207, 96, 23]);
        assert_eq!(hsl_to_rgb(0.0, 1.0, 0.5), [255, 0, 0]);
        assert_eq!(hsl_to_rgb(120.0, 1.0, 0.5), [0, 255, 0]);
        assert_eq!(model(MODEL_HUES.len()), model(0), "hues go around");
        let sum = |c: [u8; 3]| c.iter().map(|&v| v as u32).sum::<u32>();
        assert!(sum(model_shade(1, 0, 8)) < sum(model_shade(1, 7, 8)));
    }

    #[test]
    fn a_leg_reads_its_worst_joint() {
        use Torque::*;
        assert_eq!(LegTorque::of([Full, Full]), LegTorque::Full);
        assert_eq!(LegTorque::of([Full, Pinned(0.4)]), LegTorque::Pinned);
        assert_eq!(
            LegTorque::of([Reduced(0.9), Pinned(0.4)]),
            LegTorque::Reduced
        );
        assert_eq!(LegTorque::of([Reduced(0.9), Dead]), LegTorque::Dead);
        let names: Vec<_> = LegTorque::ALL.iter().map(|l| l.stance_name()).collect();
        assert!(names.windows(2).all(|w| w[0] != w[1]));
    }
}
