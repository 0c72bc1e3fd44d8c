//! How a measurement program was started. `cargo bench --bench NAME` passes `--bench` and gets the
//! whole measurement; `cargo test` runs the same program (the bench targets set `test = true`)
//! without it, as a quick check that every figure it prints is finite.

/// Whether `cargo bench` started this program (it passes `--bench` to a bench without a harness).
pub fn benched() -> bool {
    std::env::args().any(|a| a == "--bench")
}

/// `Err` naming `what` when any of `values` is NaN, infinite or negative: a measurement that
/// prints one of those has gone wrong, and the program then exits non-zero.
pub fn check_finite(what: &str, values: &[f64]) -> Result<(), String> {
    match values.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
        Some(v) => Err(format!(
            "{what}: a figure is {v}, not a finite non-negative number"
        )),
        None => Ok(()),
    }
}
