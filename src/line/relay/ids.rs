//! The relay's hash maps, each hashed by one multiplication: those keyed by a unit id
//! or a connection id, and those keyed by a read (its unit, function, address and
//! count).
//!
//! The relay looks these up several times a transaction (a unit's health and learned
//! timeout, a master's queue and share, a read waiting that another may join). std's
//! default hasher (SipHash) resists keys chosen to collide; it took 4 % of the
//! gateway's instructions a transaction for the reads' map alone (callgrind,
//! docs/performance.md "Instructions a transaction, counted"). A unit id is one of
//! 256 values and a connection id is a counter the gateway hands out, so neither an
//! attacker's nor anyone's choice: those are hashed plainly. A read's key is a
//! master's choice, so its maps mix in a secret seed of their own before the
//! multiplication; and such a map holds at most the queue's depth (the waiting reads)
//! or the cache's bound of entries, so even keys that collided would cost a scan of
//! that many, no more.

use std::collections::HashMap;
use std::hash::{BuildHasher, BuildHasherDefault, Hasher, RandomState};

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

/// A map from a key a master chooses (a read's): [`Seeded`] hashing.
pub(crate) type KeyMap<K, V> = HashMap<K, V, Seeded>;

/// Hashes with a secret seed drawn for each map (from std's own random keys), then a
/// multiplication folded onto itself, so that the low bits the table indexes by
/// depend on every bit of the key.
#[derive(Clone, Copy)]
pub(crate) struct Seeded(u64);

impl Default for Seeded {
    fn default() -> Self {
        Seeded(RandomState::new().hash_one(0u8))
    }
}

impl BuildHasher for Seeded {
    type Hasher = SeededHasher;
    fn build_hasher(&self) -> SeededHasher {
        SeededHasher(self.0)
    }
}

pub(crate) struct SeededHasher(u64);

/// An odd constant with its bits spread (PCG's multiplier).
const MIX: u64 = 0x5851_F42D_4C95_7F2D;

impl Hasher for SeededHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for chunk in bytes.chunks(8) {
            let mut word = [0u8; 8];
            word[..chunk.len()].copy_from_slice(chunk);
            self.write_u64(u64::from_le_bytes(word));
        }
    }

    fn write_u64(&mut self, n: u64) {
        let full = u128::from(self.0 ^ n) * u128::from(MIX);
        self.0 = (full as u64) ^ ((full >> 64) as u64);
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

    #[test]
    fn keys_that_differ_only_in_high_bits_spread_over_the_low_ones() {
        // The table indexes by the low bits: a read's address in the key's high bytes
        // must still move them.
        let b = Seeded::default();
        let low: std::collections::HashSet<u64> = (0u64..256)
            .map(|addr_hi| b.hash_one(addr_hi << 40) & 0xFF)
            .collect();
        assert!(low.len() > 120, "{} of 256 low bytes", low.len());
        // Two maps draw two seeds.
        assert_ne!(Seeded::default().hash_one(1u64), b.hash_one(1u64));
        let mut m: KeyMap<u64, u64> = KeyMap::default();
        for k in 0..5000u64 {
            m.insert(k << 24, k);
        }
        assert!((0..5000u64).all(|k| m[&(k << 24)] == k));
    }
}
