//! Elementwise loops compiled three times — for AVX-512, for AVX2 + FMA and for baseline x86-64
//! (the crate's target) — with the widest the CPU has chosen at run time.
//!
//! Why three: the LSTM's gate arithmetic runs at twice the speed on 16 lanes as on 8 (Zen 4,
//! docs/training.md#speed), and a build for one CPU would not run on another. Only for loops of
//! independent IEEE operations per element (or per column): no sum across lanes and no
//! multiply–add fused unasked (Rust never contracts), so every tier gives the same bits — a
//! checkpoint acts identically on every CPU. The kernels' tests compare the tiers bit for bit.

/// Defines `fn NAME` and a module `NAME` beside it holding the tiers (`plain`, and on x86-64
/// `avx2` and `avx512`, each `unsafe`: the caller checks the CPU); `NAME` calls the widest the
/// CPU has. The body sees the enclosing module's items.
macro_rules! vectorised {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                if std::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU has AVX-512F, and so AVX2 and FMA (just checked).
                    return unsafe { $name::avx512($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU has AVX2 and FMA (just checked).
                    return unsafe { $name::avx2($($arg),*) };
                }
            }
            $name::plain($($arg),*)
        }

        #[doc(hidden)]
        #[allow(dead_code, clippy::too_many_arguments)]
        $vis mod $name {
            #[allow(unused_imports)]
            use super::*;

            #[inline(always)]
            pub fn plain($($arg: $ty),*) $body

            /// # Safety
            /// The CPU must have AVX2 and FMA.
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            pub unsafe fn avx2($($arg: $ty),*) {
                plain($($arg),*)
            }

            /// # Safety
            /// The CPU must have AVX-512F.
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx2,fma")]
            pub unsafe fn avx512($($arg: $ty),*) {
                plain($($arg),*)
            }
        }
    };
}
pub(crate) use vectorised;

/// The tiers this CPU can run, widest last (for tests that compare them).
#[cfg(test)]
pub(crate) fn tiers() -> Vec<&'static str> {
    let mut tiers = vec!["plain"];
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            tiers.push("avx2");
        }
        if std::is_x86_feature_detected!("avx512f") {
            tiers.push("avx512");
        }
    }
    tiers
}

/// Calls tier `$tier` (a name from [`tiers`]) of a [`vectorised`] function; for tests.
#[cfg(test)]
macro_rules! call_tier {
    ($tier:expr, $name:path, $($arg:expr),* $(,)?) => {{
        use $name as tiers_of;
        match $tier {
            // SAFETY: `tiers()` lists only what this CPU has.
            #[cfg(target_arch = "x86_64")]
            "avx2" => unsafe { tiers_of::avx2($($arg),*) },
            #[cfg(target_arch = "x86_64")]
            "avx512" => unsafe { tiers_of::avx512($($arg),*) },
            _ => tiers_of::plain($($arg),*),
        }
    }};
}
#[cfg(test)]
pub(crate) use call_tier;
