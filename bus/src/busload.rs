//! Worst-case CAN bus load of a cyclic configuration.
//!
//! A classic base-format data frame of n bytes is 8n + 47 bits before stuffing; of those,
//! 34 + 8n bits are subject to bit stuffing, which in the worst case adds one bit per four
//! after the first: ⌊(34 + 8n − 1)/4⌋. (Interframe space included in the 47.)

/// Worst-case bits on the wire for one standard-id data frame with `n` data bytes.
pub fn frame_bits(n: usize) -> u32 {
    let n = n.min(8) as u32;
    8 * n + 47 + (34 + 8 * n - 1) / 4
}

/// Bus load (0…1+) of frames with the given data lengths sent once per `cycle_s` at
/// `bitrate` bit/s.
pub fn load(frame_lens: &[usize], cycle_s: f64, bitrate: u32) -> f64 {
    let bits: u32 = frame_lens.iter().map(|&n| frame_bits(n)).sum();
    bits as f64 / (cycle_s * bitrate as f64)
}

/// The cyclic frames of `drives` CiA 402 drives in CSP with one RPDO of `rpdo_len` bytes
/// and one TPDO of `tpdo_len` bytes each, plus the SYNC.
pub fn csp_frames(drives: usize, rpdo_len: usize, tpdo_len: usize) -> Vec<usize> {
    let mut v = Vec::with_capacity(2 * drives + 1);
    for _ in 0..drives {
        v.push(rpdo_len);
        v.push(tpdo_len);
    }
    v.push(0); // SYNC
    v
}

/// The shortest cycle (in whole 0.25 ms steps) whose load stays at or under `max_load`.
pub fn shortest_cycle_s(frame_lens: &[usize], bitrate: u32, max_load: f64) -> f64 {
    let bits: u32 = frame_lens.iter().map(|&n| frame_bits(n)).sum();
    let min = bits as f64 / (bitrate as f64 * max_load);
    (min / 0.00025).ceil() * 0.00025
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_bits_worst_case() {
        assert_eq!(frame_bits(0), 55);
        assert_eq!(frame_bits(8), 135);
        assert_eq!(frame_bits(6), 115);
    }

    #[test]
    fn three_drives_at_1mbit() {
        let f = csp_frames(3, 6, 6);
        let l1 = load(&f, 0.001, 1_000_000);
        let l2 = load(&f, 0.002, 1_000_000);
        assert!((l1 - 0.745).abs() < 0.001, "{l1}");
        assert!((l2 - 0.3725).abs() < 0.001, "{l2}");
        assert!((shortest_cycle_s(&f, 1_000_000, 0.8) - 0.001).abs() < 1e-12);
        // 8 drives do not fit 1 ms at 80 %.
        let f8 = csp_frames(8, 6, 6);
        assert!(load(&f8, 0.001, 1_000_000) > 0.8);
        assert!((shortest_cycle_s(&f8, 1_000_000, 0.8) - 0.0025).abs() < 1e-12);
        // A 7-byte TPDO (statusword, position, mode display): 125 bits each.
        let f7 = csp_frames(3, 6, 7);
        assert!((load(&f7, 0.002, 1_000_000) - 0.3875).abs() < 1e-9);
        assert!((shortest_cycle_s(&f7, 1_000_000, 0.8) - 0.001).abs() < 1e-12);
    }
}
