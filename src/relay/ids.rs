//! Hash maps keyed by a unit id or a connection id, hashed by one multiplication.
//!
//! The relay looks these up several times a transaction (a unit's health and learned
//! timeout, a master's queue and share). std's default hasher (SipHash) resists keys
//! chosen to collide, which these cannot be: a unit id is one of 256 values and a
//! connection id is a counter the gateway hands out, so neither an attacker's nor
//! anyone's choice. Keys a master chooses (a read's address and count) keep std's
//! hasher.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// A map from a unit id (`u8`) or a connection id (`u64`).
pub(crate) type IdMap<K, V> = HashMap<K, V, BuildHasherDefault<IdHasher>>;

/// Fibonacci hashing: the key times 2⁶⁴/φ, so that the top bits (which the table
/// reads first) differ between neighbouring ids.
#[derive(Default)]
pub(crate) struct IdHasher(u64);

const PHI: u64 = 0x9E37_79B9_7F4A_7C15;

impl Hasher for IdHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        // Not reached by the integer keys above; any other key still hashes.
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u8(&mut self, n: u8) {
        self.write_u64(u64::from(n));
    }

    fn write_u64(&mut self, n: u64) {
        self.0 = (self.0.rotate_left(5) ^ n).wrapping_mul(PHI);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::hash::BuildHasher;

    #[test]
    fn neighbouring_ids_differ_in_the_top_bits() {
        let b = BuildHasherDefault::<IdHasher>::default();
        let tops: std::collections::HashSet<u64> =
            (0u8..=255).map(|u| b.hash_one(u) >> 57).collect();
        // 256 unit ids over the 128 top-7-bit tags: most tags used, none crowded.
        assert!(tops.len() > 100, "{} tags", tops.len());
        let conns: std::collections::HashSet<u64> =
            (1u64..=1000).map(|c| b.hash_one(c) >> 54).collect();
        assert!(conns.len() > 600, "{} of 1024 buckets", conns.len());
    }

    #[test]
    fn a_map_keeps_what_it_is_given() {
        let mut m: IdMap<u64, u64> = IdMap::default();
        for c in 0..10_000u64 {
            m.insert(c, c * 3);
        }
        assert!((0..10_000u64).all(|c| m[&c] == c * 3));
        let mut u: IdMap<u8, u8> = IdMap::default();
        for x in 0..=255u8 {
            u.insert(x, x ^ 0x5A);
        }
        assert!((0..=255u8).all(|x| u[&x] == x ^ 0x5A));
    }
}
