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

/// Each model's hue, by lane (the first model, the second, a fork …): orange, blue, teal,
/// magenta, olive, grey — far apart from each other and from the torque colours' ramp.
pub const MODEL: [[u8; 3]; 6] = [
    [255, 140, 0],
    [60, 120, 230],
    [0, 170, 170],
    [200, 60, 160],
    [150, 150, 40],
    [150, 150, 150],
];

/// The hue of lane `index` (models beyond six reuse hues in order).
pub fn model(index: usize) -> [u8; 3] {
    MODEL[index % MODEL.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

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
        all.extend(MODEL);
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                assert_ne!(a, b);
            }
        }
    }
}
