//! Subnormal numbers flushed to zero for the span of a dense kernel (docs/theory.md §7).
//!
//! The covariances of a long chain hold correlations that decay geometrically with the
//! distance between subsystems, down to and below the smallest normal `f64` (about
//! `2.2e-308`). Arithmetic on subnormal numbers is tens of times slower on x86-64 (a microcode
//! assist per operation): on the platoon at 800 lifted states it made the centralized filter's
//! products 3.4 times slower. Flushing them changes a result by less than `2.2e-308` in
//! absolute value per operation, far below the rounding of any entry that matters.
//!
//! On x86-64 this sets the FTZ and DAZ bits of the thread's MXCSR register and restores the
//! previous value when the guard is dropped; elsewhere it does nothing (the results are the
//! same, only slower where subnormals appear).
#![allow(unsafe_code)]

use std::marker::PhantomData;

/// While alive, subnormal inputs and results of floating-point operations on this thread
/// are read and written as zero. Hold it only around code that does not hand work to other
/// threads: the mode is per thread.
pub struct FlushSubnormals {
    #[cfg(target_arch = "x86_64")]
    saved: u32,
    /// The mode belongs to the thread that set it: the guard is neither `Send` nor `Sync`.
    _thread: PhantomData<*const ()>,
}

/// MXCSR's flush-to-zero (results) and denormals-are-zero (inputs) bits.
#[cfg(target_arch = "x86_64")]
const FTZ_DAZ: u32 = 0x8040;

impl FlushSubnormals {
    #[cfg(target_arch = "x86_64")]
    pub fn new() -> Self {
        let mut saved: u32 = 0;
        // SAFETY: `stmxcsr` stores the 32-bit MXCSR into the local `saved`, and `ldmxcsr`
        // loads a value that differs from it only in FTZ and DAZ, which select how subnormal
        // numbers are handled and raise no exception. The stack is not used.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut saved, options(nostack));
            let flushed = saved | FTZ_DAZ;
            std::arch::asm!("ldmxcsr [{}]", in(reg) &flushed, options(nostack, readonly));
        }
        Self {
            saved,
            _thread: PhantomData,
        }
    }

    #[cfg(not(target_arch = "x86_64"))]
    pub fn new() -> Self {
        Self {
            _thread: PhantomData,
        }
    }
}

impl Default for FlushSubnormals {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(target_arch = "x86_64")]
impl Drop for FlushSubnormals {
    fn drop(&mut self) {
        // SAFETY: restores the MXCSR value that `new` read on this same thread (the guard
        // cannot move to another).
        unsafe {
            std::arch::asm!("ldmxcsr [{}]", in(reg) &self.saved, options(nostack, readonly));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subnormals_are_flushed_inside_the_guard_and_kept_after() {
        let tiny = std::hint::black_box(f64::MIN_POSITIVE);
        let half = std::hint::black_box(0.5);
        {
            let _flush = FlushSubnormals::new();
            let product = std::hint::black_box(tiny * half);
            if cfg!(target_arch = "x86_64") {
                assert_eq!(product, 0.0);
            }
        }
        let product = std::hint::black_box(tiny * half);
        assert!(product.is_subnormal());
    }
}
