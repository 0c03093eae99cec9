//! The day's sample of a long sweep that the test suite runs in part (the expert proofs, the stock goals' binding):
//! a seed that changes once a day, and a seeded shuffle that picks the same members on every machine, so a failure
//! seen on one day can be repeated by its printed seed.

/// Days since 1970 (UTC), or the value of the environment variable `env` when it holds a number.
pub fn day_seed(env: &str) -> u64 {
    std::env::var(env).ok().and_then(|s| s.parse().ok()).unwrap_or_else(|| {
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs() / 86_400)
    })
}

/// The first `n` of `items` after a shuffle seeded by `seed` (a 64-bit LCG).
pub fn seeded_pick<T>(mut items: Vec<T>, n: usize, seed: u64) -> Vec<T> {
    let mut state = seed;
    for i in (1..items.len()).rev() {
        state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        items.swap(i, (state >> 33) as usize % (i + 1));
    }
    items.truncate(n);
    items
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_seed_picks_the_same_members_and_another_seed_others() {
        let items: Vec<u32> = (0..130).collect();
        let a = seeded_pick(items.clone(), 44, 20785);
        assert_eq!(a, seeded_pick(items.clone(), 44, 20785));
        assert_ne!(a, seeded_pick(items.clone(), 44, 20786));
        let mut sorted = a.clone();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), 44, "44 distinct members");
        assert_eq!(seeded_pick(items, 500, 1).len(), 130, "never more than there are");
    }
}
