//! `log merge` writes a message once only when another input has the very same bytes at the
//! same log time on the same channel: two different messages that share their CRC32 and
//! length (built here on purpose) both survive.

use std::collections::BTreeMap;
use std::path::Path;

/// `a` with some of its last 5 bytes' bits flipped so that its CRC32 and length stay the same.
/// CRC32 is affine in the message for a fixed length, so the bit flips that keep it are the
/// kernel of a 32 × 40 matrix over GF(2): Gaussian elimination finds one.
fn crc_twin(a: &[u8]) -> Vec<u8> {
    let n = a.len();
    let base = crc32fast::hash(a);
    let flip = |mask: u64| {
        let mut b = a.to_vec();
        for j in 0..40 {
            if mask >> j & 1 == 1 {
                b[n - 5 + j / 8] ^= 1 << (j % 8);
            }
        }
        b
    };
    // Basis of the CRC changes seen so far, by leading bit: (change, bits flipped).
    let mut basis: Vec<(u32, u64)> = Vec::new();
    for j in 0..40 {
        let (mut v, mut m) = (crc32fast::hash(&flip(1 << j)) ^ base, 1u64 << j);
        for &(bv, bm) in &basis {
            if v ^ bv < v {
                (v, m) = (v ^ bv, m ^ bm);
            }
        }
        if v == 0 {
            return flip(m);
        }
        basis.push((v, m));
        basis.sort_by_key(|b| std::cmp::Reverse(b.0));
    }
    unreachable!("40 vectors in a 32-dimensional space are dependent")
}

fn write_log(path: &Path, messages: &[(u64, &[u8])]) {
    let mut w = mcap::Writer::new(std::io::BufWriter::new(std::fs::File::create(path).unwrap())).unwrap();
    let schema = w.add_schema("twinswarm.Test", "protobuf", b"\x0a\x00").unwrap();
    let channel = w.add_channel(schema, "/copters/state", "protobuf", &BTreeMap::new()).unwrap();
    for (seq, (t, data)) in messages.iter().enumerate() {
        let header =
            mcap::records::MessageHeader { channel_id: channel, sequence: seq as u32, log_time: *t, publish_time: *t };
        w.write_to_known_channel(&header, data).unwrap();
    }
    w.finish().unwrap();
}

fn read_messages(path: &Path) -> Vec<(u64, Vec<u8>)> {
    let data = std::fs::read(path).unwrap();
    let mut out: Vec<(u64, Vec<u8>)> = mcap::MessageStream::new(&data)
        .unwrap()
        .map(|m| m.unwrap())
        .map(|m| (m.log_time, m.data.into_owned()))
        .collect();
    out.sort();
    out
}

#[test]
fn messages_sharing_crc_and_length_are_both_kept_and_equal_bytes_written_once() {
    let a: Vec<u8> = b"copter 17 at (1.25, -0.50, 0.98) m, crashed: no".to_vec();
    let b = crc_twin(&a);
    assert_ne!(a, b);
    assert_eq!((crc32fast::hash(&a), a.len()), (crc32fast::hash(&b), b.len()), "built to collide");
    let same: &[u8] = b"the static scene, seen by both shards";

    let dir = std::env::temp_dir().join(format!("twinswarm-merge-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (one, two, out) = (dir.join("one.mcap"), dir.join("two.mcap"), dir.join("merged.mcap"));
    write_log(&one, &[(1_000, &a), (1_000, same)]);
    write_log(&two, &[(1_000, &b), (1_000, same)]);

    let report = bridge::log::merge(&[one, two], &out).unwrap();
    assert_eq!(report.duplicates, 1, "only the byte-identical message is a duplicate");
    assert_eq!(report.undeclared, vec![0, 0]);
    let merged = read_messages(&out);
    let mut want = vec![(1_000, a), (1_000, b), (1_000, same.to_vec())];
    want.sort();
    assert_eq!(merged, want, "nothing lost, nothing doubled");
    std::fs::remove_dir_all(&dir).unwrap();
}
