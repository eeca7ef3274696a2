//! The project's seeded random streams (`swarmcore/streams.py`), as far as an agent needs
//! them: `stream(seed, purpose, keys...)` is numpy's `Generator(PCG64(SeedSequence(seed,
//! spawn_key=(crc32(purpose), *keys))))`, and `random()` its first double. The drop fault's
//! losses (`swarmrt.protocol.message_dropped`) are drawn by the agent and by the world from
//! it, so both must make the same draw.

/// zlib's CRC-32 of `data` (`zlib.crc32`).
pub fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

const INIT_A: u32 = 0x43b0_d7e5;
const MULT_A: u32 = 0x931e_8875;
const INIT_B: u32 = 0x8b51_f9dd;
const MULT_B: u32 = 0x58f3_8ded;
const MIX_MULT_L: u32 = 0xca01_f9dd;
const MIX_MULT_R: u32 = 0x4973_f715;
const XSHIFT: u32 = 16;
const POOL_SIZE: usize = 4;

fn hashmix(value: u32, hash_const: &mut u32) -> u32 {
    let mut v = value ^ *hash_const;
    *hash_const = hash_const.wrapping_mul(MULT_A);
    v = v.wrapping_mul(*hash_const);
    v ^ (v >> XSHIFT)
}

fn mix(x: u32, y: u32) -> u32 {
    let r = MIX_MULT_L.wrapping_mul(x).wrapping_sub(MIX_MULT_R.wrapping_mul(y));
    r ^ (r >> XSHIFT)
}

/// A non-negative integer as numpy's SeedSequence takes it: 32-bit words, least first.
fn words(mut n: u64) -> Vec<u32> {
    if n == 0 {
        return vec![0];
    }
    let mut out = vec![];
    while n > 0 {
        out.push((n & 0xFFFF_FFFF) as u32);
        n >>= 32;
    }
    out
}

/// numpy's `SeedSequence(entropy, spawn_key=spawn_key).generate_state(n_words64, uint64)`.
fn seed_sequence_state(entropy: u64, spawn_key: &[u64], n_words64: usize) -> Vec<u64> {
    let mut run = words(entropy);
    let spawn: Vec<u32> = spawn_key.iter().flat_map(|&k| words(k)).collect();
    if !spawn.is_empty() && run.len() < POOL_SIZE {
        run.resize(POOL_SIZE, 0);
    }
    let entropy_array: Vec<u32> = run.into_iter().chain(spawn).collect();
    let mut pool = [0u32; POOL_SIZE];
    let mut hc = INIT_A;
    for (i, slot) in pool.iter_mut().enumerate() {
        *slot = hashmix(entropy_array.get(i).copied().unwrap_or(0), &mut hc);
    }
    for i_src in 0..POOL_SIZE {
        for i_dst in 0..POOL_SIZE {
            if i_src != i_dst {
                let h = hashmix(pool[i_src], &mut hc);
                pool[i_dst] = mix(pool[i_dst], h);
            }
        }
    }
    for &e in entropy_array.iter().skip(POOL_SIZE) {
        for slot in pool.iter_mut() {
            let h = hashmix(e, &mut hc);
            *slot = mix(*slot, h);
        }
    }
    let mut hb = INIT_B;
    let n32 = 2 * n_words64;
    let mut state32 = Vec::with_capacity(n32);
    for i in 0..n32 {
        let mut d = pool[i % POOL_SIZE];
        d ^= hb;
        hb = hb.wrapping_mul(MULT_B);
        d = d.wrapping_mul(hb);
        d ^= d >> XSHIFT;
        state32.push(d);
    }
    state32.chunks(2).map(|c| u64::from(c[0]) | (u64::from(c[1]) << 32)).collect()
}

/// numpy's PCG64 (XSL-RR 128/64).
pub struct Pcg64 {
    state: u128,
    inc: u128,
}

const PCG_MULT: u128 = (0x2360_ED05_1FC6_5DA4u128 << 64) | 0x4385_DF64_9FCC_F645u128;

impl Pcg64 {
    fn step(&mut self) {
        self.state = self.state.wrapping_mul(PCG_MULT).wrapping_add(self.inc);
    }

    fn from_seed(s: &[u64]) -> Pcg64 {
        let initstate = (u128::from(s[0]) << 64) | u128::from(s[1]);
        let initseq = (u128::from(s[2]) << 64) | u128::from(s[3]);
        let mut g = Pcg64 { state: 0, inc: (initseq << 1) | 1 };
        g.step();
        g.state = g.state.wrapping_add(initstate);
        g.step();
        g
    }

    pub fn next_u64(&mut self) -> u64 {
        self.step();
        let s = self.state;
        let rot = (s >> 122) as u32;
        (((s >> 64) as u64) ^ (s as u64)).rotate_right(rot)
    }

    /// `Generator.random()`: a double in [0, 1).
    pub fn random(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
}

/// `swarmcore.streams.stream(seed, purpose, *keys)`.
pub fn stream(seed: u64, purpose: &str, keys: &[u64]) -> Pcg64 {
    let mut spawn = vec![u64::from(crc32(purpose.as_bytes()))];
    spawn.extend_from_slice(keys);
    Pcg64::from_seed(&seed_sequence_state(seed, &spawn, 4))
}

/// What a drop fault loses (`swarmrt.protocol.DROP_BATCH`, `DROP_ESTIMATE`).
pub const DROP_BATCH: u64 = 0;
pub const DROP_ESTIMATE: u64 = 1;

/// `swarmrt.protocol.message_dropped`: whether satellite `sat`'s message `what` of step `k`
/// is lost at `rate`.
pub fn message_dropped(seed: u64, sat: u64, k: u64, what: u64, rate: f64) -> bool {
    rate > 0.0 && stream(seed, "drop", &[sat, k, what]).random() < rate
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_of_a_known_string() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    /// Values printed by numpy 2.x: `swarmcore.streams.stream(seed, purpose, *keys).random()`.
    #[test]
    fn draws_equal_numpys() {
        for (seed, purpose, keys, want) in crate::streams::tests::EXPECTED {
            let got = stream(*seed, purpose, keys).random();
            assert_eq!(got.to_bits(), want.to_bits(), "stream({seed}, {purpose}, {keys:?}) = {got:e}, numpy {want:e}");
        }
    }

    pub(crate) const EXPECTED: &[(u64, &str, &[u64], f64)] = &[
        (1, "drop", &[0, 0, 0], 0.7156542638866039),
        (1, "drop", &[3, 17, 1], 0.09122071260458153),
        (0, "drop", &[2, 5, 0], 0.3178859194598971),
        (123456789, "drop", &[1, 60, 0], 0.9398317348277845),
        (1099511627781, "drop", &[7, 8589934592, 1], 0.24258991623919157),
        (42, "init_est", &[3], 0.2991373620349346),
        // docs/agent-contract.md, C12's table.
        (0, "drop", &[0, 0, 0], 0.4702575520061659),
        (3, "drop", &[1, 12, 0], 0.026932796663412195),
        (3, "drop", &[1, 12, 1], 0.5379619002921988),
        (7, "drop", &[2, 100, 0], 0.6064232912111428),
    ];
}
