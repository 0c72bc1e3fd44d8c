//! Wider vectors where the processor has them, with the same arithmetic.
//!
//! The crate builds for the default x86-64 target (SSE2), so the loops that LLVM vectorises
//! work two `f64` lanes at a time. [`with_avx2!`] compiles a block a second time with AVX2
//! enabled (four lanes, three-operand instructions) and runs that copy when the processor
//! reports AVX2 at run time. Rust never fuses a multiply and an add on its own, and AVX2 alone
//! has no fused multiply-add, so both copies compute the same values to the bit; only the
//! width of the instructions differs. Only what is inlined into the block gets the wider
//! build: the Euler step's passes over the nodes, not the calls they make.

#[cfg(test)]
use std::cell::Cell;

#[cfg(test)]
thread_local! {
    /// Tests set this to run the default build on their own thread ([`without_avx2`]).
    static DEFAULT_BUILD_ONLY: Cell<bool> = const { Cell::new(false) };
}

/// True when [`with_avx2!`] runs its AVX2 build: the processor has AVX2 (a cached check).
#[cfg(target_arch = "x86_64")]
#[inline]
pub(crate) fn avx2_available() -> bool {
    #[cfg(test)]
    if DEFAULT_BUILD_ONLY.with(Cell::get) {
        return false;
    }
    std::arch::is_x86_feature_detected!("avx2")
}

/// Runs `f` with [`with_avx2!`] taking the default build on this thread, so that a test can
/// compare the two builds.
#[cfg(test)]
pub(crate) fn without_avx2<R>(f: impl FnOnce() -> R) -> R {
    DEFAULT_BUILD_ONLY.with(|c| c.set(true));
    let r = f();
    DEFAULT_BUILD_ONLY.with(|c| c.set(false));
    r
}

/// Evaluates the block `$body` compiled for AVX2 when the processor has it, and the default
/// build of the same block otherwise. The block becomes a closure inlined into a function with
/// AVX2 enabled.
macro_rules! with_avx2 {
    ($body:block) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2")]
            fn avx2<R>(body: impl FnOnce() -> R) -> R {
                body()
            }
            if $crate::model::simd::avx2_available() {
                // SAFETY: the processor has AVX2, the only feature `avx2` enables.
                unsafe {
                    avx2(
                        #[inline(always)]
                        || $body,
                    )
                }
            } else {
                $body
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            $body
        }
    }};
}

pub(crate) use with_avx2;
