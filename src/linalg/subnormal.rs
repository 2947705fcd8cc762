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
//!
//! The guard also ends the kernel's use of the wide vector registers. faer's products run
//! hand-written AVX-512 kernels that return with the upper halves of the vector registers in
//! use (no `vzeroupper`); every SSE instruction of the code compiled for baseline x86-64 that
//! runs after them (the innovation check, the step's own loops) then waits on those halves. On
//! the platoon at 40 lifted states that made the innovation check twice as slow. On leaving,
//! the guard clears them (`vzeroupper`, where the processor has AVX), which changes no value.
#![allow(unsafe_code)]

use std::marker::PhantomData;

/// While alive, subnormal inputs and results of floating-point operations on this thread
/// are read and written as zero; when dropped, the upper halves of the vector registers are
/// cleared. Hold it only around code that does not hand work to other threads: the mode is
/// per thread.
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
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the processor has AVX, so `vzeroupper` exists; it zeroes bits 128 and up
            // of the vector registers, which no Rust value lives in across this point (the
            // calling convention leaves them undefined at a call).
            unsafe {
                std::arch::asm!("vzeroupper", options(nostack, nomem, preserves_flags));
            }
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

    /// The state components in use (XINUSE: `xgetbv` with `ecx = 1`), where the processor
    /// reports them.
    #[cfg(target_arch = "x86_64")]
    fn state_in_use() -> Option<u64> {
        if !std::arch::is_x86_feature_detected!("xsave") {
            return None;
        }
        // CPUID leaf 0xD exists where XSAVE does; bit 2 of sub-leaf 1's EAX says whether
        // `xgetbv` takes `ecx = 1`.
        let leaf = std::arch::x86_64::__cpuid_count(0xd, 1);
        if leaf.eax & 4 == 0 {
            return None;
        }
        let (low, high): (u32, u32);
        // SAFETY: supported, as checked above; it only reads a register.
        unsafe {
            std::arch::asm!("xgetbv", in("ecx") 1u32, out("eax") low, out("edx") high,
                options(nomem, nostack, preserves_flags));
        }
        Some(u64::from(high) << 32 | u64::from(low))
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn a_kernel_leaves_the_vector_registers_upper_halves_clear() {
        use faer::{Accum, Mat, Par};
        // XINUSE bits: the upper halves of YMM0-15 and of ZMM0-15.
        const UPPER_HALVES: u64 = 1 << 2 | 1 << 6;
        let Some(before) = state_in_use() else {
            return;
        };
        let a = Mat::<f64>::from_fn(64, 64, |i, j| (i + 2 * j) as f64);
        let mut product = Mat::<f64>::zeros(64, 64);
        let inside = {
            let _flush = FlushSubnormals::new();
            faer::linalg::matmul::matmul(
                product.as_mut(),
                Accum::Replace,
                a.as_ref(),
                a.as_ref(),
                1.0,
                Par::Seq,
            );
            state_in_use().unwrap()
        };
        let after = state_in_use().unwrap();
        assert_eq!(
            product[(1, 1)],
            (0..64).map(|k| ((1 + 2 * k) * (k + 2)) as f64).sum::<f64>()
        );
        if inside & UPPER_HALVES == 0 {
            // No wide kernel on this processor: nothing to clear.
            return;
        }
        // A processor may report a component in use that is in its initial state; this
        // check needs one that reports the halves clear once `vzeroupper` has run.
        // SAFETY: the kernel used the upper halves, so the processor has AVX.
        unsafe {
            std::arch::asm!("vzeroupper", options(nostack, nomem, preserves_flags));
        }
        if state_in_use().unwrap() & UPPER_HALVES != 0 {
            return;
        }
        assert_eq!(
            after & UPPER_HALVES,
            0,
            "XINUSE {before:#x}, {inside:#x} in the kernel's span, {after:#x} after it"
        );
    }
}
