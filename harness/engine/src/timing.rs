//! The silence before an RTU answer, measured over a whole run (serial line guide 2.5.1.1: "message frames are
//! separated by a silent interval of at least 3.5 character times", a MUST).
//!
//! User space cannot see the line: the request's last byte leaves the UART some time after the write started,
//! and an answer's first byte is seen some time after it arrived (a USB adapter adds milliseconds). So each
//! answer gets an upper bound of its real gap: the time from the start of the write of the request's last
//! piece to the answer's first byte being seen, less the time the piece takes on the line and one character
//! (the first byte of the answer must have been received whole). An upper bound below t3.5 is an answer that
//! surely began inside the silence; one above says nothing. The bound is exact on the simulator's virtual
//! line, and a native UART comes close; behind a USB adapter only gross violations show. On a
//! pseudo-terminal, over RTU over TCP, or for an in-process device there is no line to measure.
//!
//! Every answer is measured, and one case (`rtu/timing/inter-frame-silence`, [`crate::cases::Tag::RunTiming`],
//! run after the others) judges them all at once: one finding per run instead of one per case.

use std::time::Duration;

/// Samples kept for the distribution (a long run keeps its first ones).
const MAX_SAMPLES: usize = 100_000;
/// Answers inside the silence named in the finding (the count is exact).
const MAX_NAMED: usize = 10;

/// The gaps measured before the answers of a run.
#[derive(Clone, Debug, Default)]
pub struct AnswerGaps {
    /// The t3.5 of the line.
    pub t3_5: Duration,
    /// Upper bounds of the gaps, in the order measured (at most [`MAX_SAMPLES`]).
    samples: Vec<Duration>,
    /// Answers measured.
    pub measured: u64,
    /// Answers whose gap was surely below t3.5.
    pub inside: u64,
    /// The first cases with such answers: case id and the smallest upper bound among them.
    named: Vec<(String, Duration)>,
}

impl AnswerGaps {
    /// Record one answer: its first byte seen `first_at` (target clock), the write of the request's last
    /// piece of `last_piece` bytes begun at `write_began`, on a line of `timing`.
    pub fn record(
        &mut self,
        case: &str,
        timing: codec::RtuTiming,
        write_began: Duration,
        last_piece: usize,
        first_at: Duration,
    ) {
        self.t3_5 = timing.t3_5;
        let gap = first_at
            .saturating_sub(write_began)
            .saturating_sub(timing.transmit_time(last_piece))
            .saturating_sub(timing.char_time);
        self.measured += 1;
        if self.samples.len() < MAX_SAMPLES {
            self.samples.push(gap);
        }
        if gap < timing.t3_5 {
            self.inside += 1;
            let full = self.named.len() >= MAX_NAMED;
            match self.named.iter_mut().find(|(c, _)| c == case) {
                Some((_, g)) => *g = (*g).min(gap),
                None if !full => self.named.push((case.to_string(), gap)),
                None => {}
            }
        }
    }

    /// min / 10th percentile / median / 90th percentile / max of the gaps kept, in µs.
    pub fn distribution(&self) -> Option<[u128; 5]> {
        let mut s: Vec<Duration> = self.samples.clone();
        if s.is_empty() {
            return None;
        }
        s.sort_unstable();
        let at = |q: usize| s[(s.len() - 1) * q / 100].as_micros();
        Some([at(0), at(10), at(50), at(90), at(100)])
    }

    /// The judgement of the whole run: `None` when nothing was measured, else the findings (empty: every
    /// answer kept the silence) and a note with the distribution.
    pub fn judge(&self) -> Option<(Vec<String>, String)> {
        let [min, p10, p50, p90, max] = self.distribution()?;
        let note = format!(
            "{} answers measured; gaps after the request (upper bounds, µs): min {min}, p10 {p10}, median {p50}, p90 {p90}, max {max}; t3.5 = {} µs",
            self.measured,
            self.t3_5.as_micros()
        );
        if self.inside == 0 {
            return Some((Vec::new(), note));
        }
        let named: Vec<String> = self
            .named
            .iter()
            .map(|(case, gap)| format!("{case} (≤ {} µs)", gap.as_micros()))
            .collect();
        Some((
            vec![format!(
                "{} of {} answers began inside the 3.5-character silence that must separate frames (t3.5 = {} µs; serial line guide 2.5.1.1), in: {}{}",
                self.inside,
                self.measured,
                self.t3_5.as_micros(),
                named.join(", "),
                if self.named.len() == MAX_NAMED {
                    ", ..."
                } else {
                    ""
                }
            )],
            note,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use codec::{CharFormat, Parity, RtuTiming};

    fn timing() -> RtuTiming {
        RtuTiming::new(
            19_200,
            CharFormat {
                parity: Parity::Even,
                stop_bits: 1,
            },
        )
    }

    #[test]
    fn an_answer_after_t3_5_is_kept_and_one_at_once_is_inside() {
        let t = timing();
        let mut g = AnswerGaps::default();
        // 8 bytes written from 0; answer's first byte in at end + t3.5 + one character: a gap of t3.5.
        let end = t.transmit_time(8);
        g.record("a", t, Duration::ZERO, 8, end + t.t3_5 + t.char_time);
        assert_eq!(g.judge().expect("measured").0, Vec::<String>::new());
        // Answered right after the last byte.
        g.record("b", t, Duration::ZERO, 8, end + t.char_time);
        let (findings, note) = g.judge().expect("measured");
        assert_eq!(findings.len(), 1);
        assert!(findings[0].starts_with("1 of 2 answers"), "{findings:?}");
        assert!(findings[0].contains("b (≤ 0 µs)"), "{findings:?}");
        assert!(note.contains("2 answers measured"), "{note}");
    }
}
