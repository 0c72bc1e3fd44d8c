//! How fine a tessellation may be: from the coarsest closed surface ([`MIN_K`]) to the finest
//! whose nodes fit the memory a fit may take ([`MAX_K`]), and the one check of a k a user gives
//! ([`check_k`]).

/// The smallest k accepted: 3 rings × 3 longitudes is the coarsest closed surface.
pub const MIN_K: usize = 3;

/// Bytes a node of a fit's tessellation takes at peak with local DOFs (the model, its forces and
/// the membrane's solver): measured 1.44 KB at k = 401 and at k = 801 (`/usr/bin/time -f %M dsq
/// fit CLOUD --k K`), rounded up.
pub const BYTES_PER_NODE: usize = 1536;

/// The memory a tessellation may take: 1 GiB.
pub const TESSELLATION_MEMORY: usize = 1 << 30;

/// The largest k accepted: the finest tessellation whose nodes take at most
/// [`TESSELLATION_MEMORY`] at [`BYTES_PER_NODE`] (k = 836, 698 898 nodes). [`Tessellation::new`](super::Tessellation::new)
/// holds a larger k to it; the front ends ([`check_k`]) refuse one.
pub const MAX_K: usize = (TESSELLATION_MEMORY / BYTES_PER_NODE - 2).isqrt();

// The largest tessellation fits the memory, and one finer does not.
const _: () = assert!((MAX_K * MAX_K + 2) * BYTES_PER_NODE <= TESSELLATION_MEMORY);
const _: () = assert!(((MAX_K + 1) * (MAX_K + 1) + 2) * BYTES_PER_NODE > TESSELLATION_MEMORY);

/// Checks the tessellation parameter `k` given as the option `name`: within [[`MIN_K`],
/// [`MAX_K`]], or a one-line error naming it, its value, the range and the memory it would take.
pub fn check_k(name: &str, k: usize) -> Result<(), String> {
    if (MIN_K..=MAX_K).contains(&k) {
        return Ok(());
    }
    if k < MIN_K {
        return Err(format!(
            "{name} = {k} is out of range [{MIN_K}, {MAX_K}]: k = {MIN_K} is the coarsest closed surface"
        ));
    }
    let nodes = |k: usize| (k as u128) * (k as u128) + 2;
    let size = |k: usize| {
        let bytes = nodes(k) as f64 * BYTES_PER_NODE as f64;
        if bytes >= 1e15 {
            format!("{bytes:.1e} bytes")
        } else if bytes >= 1e12 {
            format!("{:.0} TB", bytes / 1e12)
        } else {
            format!("{:.1} GB", bytes / 1e9)
        }
    };
    Err(format!(
        "{name} = {k} is out of range [{MIN_K}, {MAX_K}]: {} nodes would take about {}, k = {MAX_K} about {}",
        nodes(k),
        size(k),
        size(MAX_K)
    ))
}
