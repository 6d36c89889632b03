//! LZF decompression (liblzf's format), which PCL writes for `DATA binary_compressed` PCD files.
//!
//! A stream is a sequence of chunks, each opened by a control byte `c`:
//! - `c < 32`: a literal run of `c + 1` bytes that follow;
//! - otherwise a back reference: length `c >> 5` (7 means "7 plus the next byte"), plus 2, and
//!   distance `((c & 31) << 8) + next byte + 1` back from the end of the output. The distance
//!   may be shorter than the length: the reference then repeats the last `distance` bytes.
//!
//! The output never grows beyond the size the caller declares, whatever the stream says.

use crate::error::{GeometryError, Result};

/// Decompress `input`, which must expand to exactly `size` bytes.
///
/// The work is linear in `size`: an overlapping back reference is copied in chunks that double
/// (a Python byte loop took 40 s for 360 MB of distance-1 references).
///
/// # Errors
/// [`GeometryError::Corrupt`] naming the input offset where the stream runs past its end,
/// refers before the start of the output, or would expand beyond `size`; and when it ends short
/// of `size`. [`GeometryError::OutOfRange`] when `size` bytes cannot be allocated.
pub fn lzf_decompress(input: &[u8], size: usize) -> Result<Vec<u8>> {
    let corrupt = |offset: usize, message: String| GeometryError::Corrupt {
        arg: "LZF data",
        offset,
        message,
    };
    let mut out = Vec::new();
    // try_reserve: a failed allocation is an error, not an abort of the process.
    out.try_reserve_exact(size).map_err(|_| {
        GeometryError::out_of_range("size", format!("of {size} bytes cannot be allocated"))
    })?;
    let mut i = 0;
    while i < input.len() {
        let start = i;
        let ctrl = usize::from(input[i]);
        i += 1;
        let length = if ctrl < 32 {
            let run = ctrl + 1;
            let literal = input.get(i..i + run).ok_or_else(|| {
                corrupt(start, format!("a literal run of {run} bytes is cut off"))
            })?;
            if out.len() + run > size {
                return Err(corrupt(
                    start,
                    format!("expands beyond the declared {size} bytes"),
                ));
            }
            out.extend_from_slice(literal);
            i += run;
            continue;
        } else if ctrl >> 5 == 7 {
            let extra = *input
                .get(i)
                .ok_or_else(|| corrupt(start, "a back reference is cut off".into()))?;
            i += 1;
            7 + usize::from(extra) + 2
        } else {
            (ctrl >> 5) + 2
        };
        let low = *input
            .get(i)
            .ok_or_else(|| corrupt(start, "a back reference is cut off".into()))?;
        i += 1;
        let distance = ((ctrl & 31) << 8) + usize::from(low) + 1;
        let Some(mut from) = out.len().checked_sub(distance) else {
            return Err(corrupt(
                start,
                format!(
                    "a back reference {distance} bytes back from byte {} of the output",
                    out.len()
                ),
            ));
        };
        if out.len() + length > size {
            return Err(corrupt(
                start,
                format!("expands beyond the declared {size} bytes"),
            ));
        }
        // When the reference overlaps its own output, the bytes already copied are the next
        // ones to copy: each chunk may be as long as everything from `from` onwards.
        let mut left = length;
        while left > 0 {
            let chunk = left.min(out.len() - from);
            out.extend_from_within(from..from + chunk);
            from += chunk;
            left -= chunk;
        }
    }
    if out.len() != size {
        return Err(corrupt(
            input.len(),
            format!(
                "the stream ends after {} of the declared {size} bytes",
                out.len()
            ),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The format as liblzf's `lzf_decompress` reads it, one byte at a time, unbounded.
    fn lzf_decompress_naive(input: &[u8]) -> Option<Vec<u8>> {
        let mut out: Vec<u8> = Vec::new();
        let mut i = 0;
        while i < input.len() {
            let ctrl = usize::from(input[i]);
            i += 1;
            if ctrl < 32 {
                out.extend_from_slice(input.get(i..i + ctrl + 1)?);
                i += ctrl + 1;
                continue;
            }
            let mut length = ctrl >> 5;
            if length == 7 {
                length += usize::from(*input.get(i)?);
                i += 1;
            }
            let distance = ((ctrl & 31) << 8) + usize::from(*input.get(i)?) + 1;
            i += 1;
            let from = out.len().checked_sub(distance)?;
            for k in 0..length + 2 {
                out.push(out[from + k]);
            }
        }
        Some(out)
    }

    #[test]
    fn a_hand_built_stream_with_an_overlapping_reference() {
        // "abc", then 5 bytes from distance 3 (overlapping: "abcab"), then 9 bytes from
        // distance 1 (the last "b" nine times), then a literal "Z".
        let stream = [2, b'a', b'b', b'c', 3 << 5, 2, 7 << 5, 0, 0, 0, b'Z'];
        let expected = b"abcabcabbbbbbbbbbZ".to_vec();
        assert_eq!(
            lzf_decompress(&stream, expected.len()),
            Ok(expected.clone())
        );
        assert_eq!(lzf_decompress_naive(&stream), Some(expected));
    }

    #[test]
    fn long_distance_one_runs_match_the_naive_decoder() {
        // One literal byte, then groups of distance-1 references of 264 bytes and literals:
        // the stream of the audit that took a Python decoder 40 s at 360 MB.
        let mut stream = vec![0, 7];
        for group in 0..200u8 {
            for _ in 0..6 {
                stream.extend_from_slice(&[0xE0, 0xFF, 0x00]);
            }
            stream.extend_from_slice(&[3, group, 1, 2, 3]);
        }
        let expected = lzf_decompress_naive(&stream).expect("a valid stream");
        assert_eq!(expected.len(), 1 + 200 * (6 * 264 + 4));
        assert_eq!(lzf_decompress(&stream, expected.len()), Ok(expected));
    }

    #[test]
    fn random_streams_agree_with_the_naive_decoder() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(14);
        for _ in 0..300 {
            let mut stream = vec![31];
            stream.extend((0..32).map(|_| rng.gen::<u8>()));
            for _ in 0..rng.gen_range(0..40) {
                if rng.gen_bool(0.3) {
                    let run = rng.gen_range(0..32u8);
                    stream.push(run);
                    stream.extend((0..=run).map(|_| rng.gen::<u8>()));
                } else {
                    // distances within the first 32 bytes, lengths 3 to 264
                    let length: u8 = rng.gen_range(1..8);
                    stream.push(length << 5);
                    if length == 7 {
                        stream.push(rng.gen());
                    }
                    stream.push(rng.gen_range(0..32));
                }
            }
            let expected = lzf_decompress_naive(&stream).expect("a valid stream");
            assert_eq!(lzf_decompress(&stream, expected.len()), Ok(expected));
        }
    }

    #[test]
    fn truncated_and_forged_streams_are_errors_naming_the_offset() {
        let message = |stream: &[u8], size: usize| lzf_decompress(stream, size).unwrap_err();
        // a literal run that claims more bytes than follow
        let err = message(&[5, b'a', b'b'], 6);
        assert!(
            matches!(err, GeometryError::Corrupt { offset: 0, .. }),
            "{err}"
        );
        assert!(err.to_string().contains("cut off"), "{err}");
        // a back reference before the start of the output
        let err = message(&[0, b'a', 1 << 5, 4], 4);
        assert!(
            matches!(err, GeometryError::Corrupt { offset: 2, .. }),
            "{err}"
        );
        // a back reference missing its distance byte, and its length byte
        assert!(message(&[0, b'a', 1 << 5], 4)
            .to_string()
            .contains("cut off"));
        assert!(message(&[0, b'a', 7 << 5], 4)
            .to_string()
            .contains("cut off"));
        // expanding beyond the declared size, by a reference and by a literal
        let err = message(&[0, b'a', 7 << 5, 255, 0], 10);
        assert!(
            err.to_string().contains("beyond the declared 10 bytes"),
            "{err}"
        );
        assert!(message(&[3, 1, 2, 3, 4], 2).to_string().contains("beyond"));
        // ending short of the declared size
        let err = message(&[0, b'a'], 2);
        assert!(
            err.to_string()
                .contains("ends after 1 of the declared 2 bytes"),
            "{err}"
        );
        assert_eq!(lzf_decompress(&[], 0), Ok(Vec::new()));
    }

    #[test]
    fn an_impossible_size_is_an_error_not_an_abort() {
        let err = lzf_decompress(&[0, b'a'], usize::MAX).unwrap_err();
        assert!(
            matches!(err, GeometryError::OutOfRange { arg: "size", .. }),
            "{err}"
        );
    }
}
