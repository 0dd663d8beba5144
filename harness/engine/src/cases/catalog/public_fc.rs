//! Positive cases for the rest of the public function code set (MODBUS Application Protocol v1.1b3 sections
//! 6.7-6.18): FC 07, 08 (the public sub-functions the profile declares), 0B, 0C, 11, 14, 15, 16 and 18, each
//! built only when the profile declares the function, each putting back what it changes.
//!
//! Values a drive chooses itself (the diagnostic register, the counters of Modbus/TCP traffic, the server id
//! of a profile that declares none) are compared in structure only; values the spec or the profile fixes
//! (an echo, the exception status outputs mapped to coils, the file records and FIFO contents the profile
//! declares, a mask write's result read back, the counters after a restart on a serial line) exactly.

use super::around::Around;
use super::{APP, Ctx, capture, exchange, pdu};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::codes::diag;
use codec::{FileRecordRef, FileRecordWrite, FunctionCode, Request};
use drives::profile::{Profile, Table};

/// One request of this family with what it needs around it: the steps that establish its precondition and
/// keep what it changes, the request and how its answer is judged, the steps that check and put back what it
/// changed; the transport tags it needs and the freedoms its answer may use. The catalog's cases here are
/// built from these, and so are the generated cases of these function codes (`cases::generated`, which may
/// alter the request itself).
#[derive(Clone, Debug)]
pub struct Exercise {
    pub before: Vec<Step>,
    pub pdu: Vec<u8>,
    pub compare: Compare,
    pub note: String,
    pub after: Vec<Step>,
    /// `RtuOnly` / `TcpOnly` where the request means something on one framing only; the safety tags are the
    /// classifier's.
    pub tags: Vec<Tag>,
    /// Freedoms (`corpus/freedoms/`) the answers may use, beyond those the reference drive decides by.
    pub freedoms: Vec<String>,
}

impl Exercise {
    fn plain(pdu: Vec<u8>, compare: Compare, note: impl Into<String>) -> Self {
        Self {
            before: Vec::new(),
            pdu,
            compare,
            note: note.into(),
            after: Vec::new(),
            tags: Vec::new(),
            freedoms: Vec::new(),
        }
    }

    /// The request inside `a` (its precondition and restores), `checks` right after the request.
    fn around(
        a: Around,
        pdu: Vec<u8>,
        compare: Compare,
        note: impl Into<String>,
        checks: Vec<Step>,
    ) -> Self {
        let (before, after) = a.split();
        let mut e = Self::plain(pdu, compare, note);
        e.before = before;
        e.after = checks;
        e.after.extend(after);
        e
    }

    /// The steps in order, as a catalog case runs them.
    fn steps(self) -> Vec<Step> {
        let mut steps = self.before;
        steps.push(exchange(Outgoing::Pdu(self.pdu), self.compare, self.note));
        steps.extend(self.after);
        steps
    }
}

/// The family, function by function.
pub(super) fn cases(cx: &mut Ctx) {
    read_exception_status(cx);
    diagnostics(cx);
    comm_event_counter_and_log(cx);
    event_log_order(cx);
    report_server_id_case(cx);
    file_records(cx);
    mask_write(cx);
    fifo(cx);
}

/// An FC 08 request with sub-function `sub` and one data word.
fn diag_pdu(sub: u16, data: u16) -> Vec<u8> {
    pdu(&Request::Diagnostics {
        sub_function: sub,
        data: data.to_be_bytes().to_vec(),
    })
}

fn declares_sub(cx: &Ctx, sub: u16) -> bool {
    cx.p.diagnostics.iter().any(|d| d.sub_function == sub)
}

/// A request the server answers with an exception: a read past the last holding register address (exception
/// 02), or, without FC 03, an unassigned public function code (0x09, exception 01).
fn exception_request(cx: &Ctx) -> Vec<u8> {
    if cx.supports(FunctionCode::READ_HOLDING_REGISTERS) || cx.supports(0x09u8) {
        pdu(&Request::ReadHoldingRegisters {
            address: 0xFFFF,
            quantity: 1,
        })
    } else {
        vec![0x09, 0, 0, 0, 1]
    }
}

/// The first of the eight coils the profile maps the exception status outputs to, where they are consecutive
/// and can be read (FC 01) and set (FC 0F).
fn exception_status_coils(cx: &Ctx) -> Option<u16> {
    let coils: Vec<u16> =
        cx.p.exception_status
            .as_ref()
            .map(|e| e.get_ref().coils.clone())
            .unwrap_or_default();
    (coils.len() == 8
        && coils.windows(2).all(|w| w[1] == w[0] + 1)
        && cx.supports(FunctionCode::WRITE_MULTIPLE_COILS)
        && cx.supports(FunctionCode::READ_COILS))
    .then(|| coils[0])
}

/// FC 07 (6.7). With `pattern`, where the profile maps the outputs to coils: the coils kept, set to the
/// pattern, the status read exactly (output 0 in the least significant bit), the coils put back. Otherwise
/// the contents are device specific and only the format is checked. `None` without FC 07.
pub fn exception_status(p: &Profile, unit: u8, pattern: Option<u8>) -> Option<Exercise> {
    let cx = Ctx::bare(p, unit);
    if !cx.supports(FunctionCode::READ_EXCEPTION_STATUS) {
        return None;
    }
    let (Some(first), Some(pattern)) = (exception_status_coils(&cx), pattern) else {
        return Some(Exercise::plain(vec![0x07], Compare::Structure, "FC 07"));
    };
    let mut a = Around::new();
    a.keep_coils(&cx, first, 8);
    a.set(exchange(
        Outgoing::Pdu(pdu(&Request::WriteMultipleCoils {
            address: first,
            quantity: 8,
            data: vec![pattern],
        })),
        Compare::Exact,
        format!("coils {first}..+8 set to 0b{pattern:08b}"),
    ));
    Some(Exercise::around(
        a,
        vec![0x07],
        Compare::Exact,
        "FC 07: output 0 in the least significant bit",
        Vec::new(),
    ))
}

/// FC 07 (6.7): the eight exception status outputs. Where the profile maps them to coils, the coils are set
/// to a pattern that reads differently bit-reversed (outputs 1 and 2 on) and the status must show it;
/// otherwise the contents are device specific and only the format is checked.
fn read_exception_status(cx: &mut Ctx) {
    let Some(e) = exception_status(cx.p, cx.unit, Some(0b0000_0110)) else {
        return;
    };
    if exception_status_coils(cx).is_some() {
        cx.push(
            "spec/app-6.7/read-exception-status/outputs".into(),
            "FC 07 reports the exception status outputs, output 0 in bit 0",
            format!("{APP}, section 6.7; the profile's [exception_status] coils"),
            "Read Exception Status returns the eight exception status outputs in one byte, the output of the lowest number in the least significant bit.",
            vec![Tag::Write],
            e.steps(),
        );
    } else {
        cx.push(
            "spec/app-6.7/read-exception-status/format".into(),
            "FC 07 answers one status byte",
            format!("{APP}, section 6.7"),
            "Read Exception Status returns the eight exception status outputs in one byte; their contents are device specific.",
            vec![],
            e.steps(),
        );
    }
}

/// FC 08 (6.8.1): the public sub-functions the profile declares. The echo and the diagnostic register on
/// every transport; the counters of Modbus/TCP traffic in structure (the spec defines them for a serial
/// line); on a serial line the NAK, busy and overrun counts after a clear exactly, the delimiter change, the
/// restart and listen only mode (whose exit is a restart: tagged destructive, skipped on a real drive unless
/// allowed).
fn diagnostics(cx: &mut Ctx) {
    if !cx.supports(FunctionCode::DIAGNOSTICS) {
        return;
    }
    let read = super::known_good_read(cx.p);
    if let Some(echo) =
        cx.p.diagnostics
            .iter()
            .find(|d| d.sub_function == diag::RETURN_QUERY_DATA)
    {
        // Four bytes, unless the manual fixes the size of the telegram (the SD2x: two).
        let mut data = vec![0x5A, 0xA5, 0x12, 0x34];
        data.truncate(echo.data_bytes.map_or(4, usize::from));
        cx.push(
            "spec/app-6.8.1/00-return-query-data".into(),
            "FC 08/00 echoes its data",
            format!("{APP}, section 6.8.1 (sub-function 00)"),
            "Return Query Data echoes the request's data field unchanged.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::Diagnostics {
                    sub_function: diag::RETURN_QUERY_DATA,
                    data: data.clone(),
                })),
                Compare::Exact,
                format!("data {}", codec::hex_spaced(&data)),
            )],
        );
        // Where the manual fixes the size, a data field of another size: echoed (6.8.1 takes any), refused
        // with 03, or not taken for a telegram (`sd2x-diagnostic-data-size`).
        if let Some(n) = echo.data_bytes {
            let sizes = [usize::from(n).saturating_sub(1), usize::from(n) + 2];
            cx.push(
                format!("profile/{}/fc08/return-query-data-size", cx.p.device.id),
                format!("FC 08/00 with a data field of other than {n} bytes"),
                format!("{APP}, section 6.8.1 (sub-function 00); the profile's manual (data field size)"),
                "Return Query Data with a data field of another size than the manual fixes is echoed, refused with exception 03, or left unanswered, the same way each time.",
                vec![],
                sizes
                    .iter()
                    .map(|&len| {
                        let data: Vec<u8> = (0..len).map(|i| 0xC3 ^ i as u8).collect();
                        exchange(
                            Outgoing::Pdu(pdu(&Request::Diagnostics {
                                sub_function: diag::RETURN_QUERY_DATA,
                                data,
                            })),
                            Compare::Exact,
                            format!("{len} data byte(s)"),
                        )
                    })
                    .collect(),
            );
        }
    }
    // Sub-functions whose data field the profile's manual does not use (6.8.1 gives 00 00), where the profile
    // does not say the drive checks it: a non-zero field is ignored or refused with 03, the same way each
    // time (`sd2x-diagnostic-unused-data`). Counter reads only: nothing changes.
    let unchecked: Vec<u16> = (diag::BUS_MESSAGE_COUNT..=diag::SERVER_NO_RESPONSE_COUNT)
        .filter(|&sub| {
            cx.p.diagnostics
                .iter()
                .any(|d| d.sub_function == sub && !d.check_data)
        })
        .collect();
    for sub in unchecked {
        cx.push(
            format!("profile/{}/fc08/unused-data/0x{sub:02X}", cx.p.device.id),
            format!("FC 08/{sub:02X} with a non-zero data field"),
            format!("{APP}, section 6.8.1 (data field 00 00) and figure 21; the profile's manual"),
            "A counter read whose data field is not 00 00 is answered as with 00 00, or refused with exception 03, the same way for every sub-function.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(diag_pdu(sub, 0x0101)),
                Compare::Structure,
                format!("08/{sub:02X} with data 0x0101"),
            )],
        );
    }
    if declares_sub(cx, diag::RETURN_DIAGNOSTIC_REGISTER) {
        cx.push(
            "spec/app-6.8.1/02-diagnostic-register".into(),
            "FC 08/02 returns the diagnostic register",
            format!("{APP}, section 6.8.1 (sub-function 02)"),
            "Return Diagnostic Register returns the 16-bit diagnostic register (its contents are device specific) under the echoed sub-function.",
            vec![],
            vec![exchange(
                Outgoing::Pdu(diag_pdu(diag::RETURN_DIAGNOSTIC_REGISTER, 0)),
                Compare::Structure,
                "08/02",
            )],
        );
    }
    if declares_sub(cx, diag::CLEAR_COUNTERS) {
        // Over Modbus/TCP the counters are the device's to define: the format only.
        let mut steps = vec![exchange(
            Outgoing::Pdu(diag_pdu(diag::CLEAR_COUNTERS, 0)),
            Compare::Exact,
            "clear counters (echo)",
        )];
        for sub in diag::BUS_MESSAGE_COUNT..=diag::BUS_CHARACTER_OVERRUN_COUNT {
            if declares_sub(cx, sub) && sub != diag::BUS_CHARACTER_OVERRUN_COUNT {
                steps.push(exchange(
                    Outgoing::Pdu(diag_pdu(sub, 0)),
                    Compare::Structure,
                    format!("08/{sub:02X}"),
                ));
            }
        }
        cx.push(
            "spec/app-6.8.1/counters/format-tcp".into(),
            "FC 08 counters over Modbus/TCP: one 16-bit count each",
            format!("{APP}, section 6.8.1 (sub-functions 0A-11)"),
            "Clear Counters is echoed; each counter sub-function returns one 16-bit count under the echoed sub-function.",
            vec![Tag::TcpOnly],
            steps,
        );
        let mut steps = vec![exchange(
            Outgoing::Pdu(diag_pdu(diag::CLEAR_COUNTERS, 0)),
            Compare::Exact,
            "clear counters",
        )];
        let mut any = false;
        for (sub, what) in [
            (diag::SERVER_NAK_COUNT, "NAK count"),
            (diag::SERVER_BUSY_COUNT, "busy count"),
            (diag::BUS_CHARACTER_OVERRUN_COUNT, "character overrun count"),
        ] {
            if declares_sub(cx, sub) {
                any = true;
                steps.push(exchange(
                    Outgoing::Pdu(diag_pdu(sub, 0)),
                    Compare::Exact,
                    what,
                ));
            }
        }
        if declares_sub(cx, diag::CLEAR_OVERRUN) {
            any = true;
            steps.push(exchange(
                Outgoing::Pdu(diag_pdu(diag::CLEAR_OVERRUN, 0)),
                Compare::Exact,
                "08/14 clear overrun counter and flag (echo)",
            ));
        }
        if any {
            cx.push(
                "spec/app-6.8.1/counters/nak-busy-overrun".into(),
                "FC 08/10, 11, 12 after a clear, and 08/14",
                format!("{APP}, section 6.8.1 (sub-functions 0A, 10, 11, 12, 14)"),
                "After Clear Counters, a server that sent no NAK or busy exception and had no character overrun returns 0 for the NAK, busy and overrun counts; Clear Overrun Counter and Flag is echoed.",
                vec![Tag::RtuOnly],
                steps,
            );
        }
    }
    if declares_sub(cx, diag::CHANGE_ASCII_DELIMITER) {
        cx.push(
            "spec/app-6.8.1/03-change-ascii-delimiter".into(),
            "FC 08/03 is echoed; the delimiter is put back to LF",
            format!("{APP}, section 6.8.1 (sub-function 03)"),
            "Change ASCII Input Delimiter (data CHAR 00) is echoed. The delimiter cannot be read: it is set back to LF, the spec's default.",
            vec![Tag::RtuOnly, Tag::Write],
            vec![
                exchange(
                    Outgoing::Pdu(diag_pdu(diag::CHANGE_ASCII_DELIMITER, 0x3A00)),
                    Compare::Exact,
                    "delimiter ':'",
                ),
                exchange(
                    Outgoing::Pdu(diag_pdu(diag::CHANGE_ASCII_DELIMITER, 0x0A00)),
                    Compare::Exact,
                    "put back LF",
                ),
            ],
        );
    }
    if declares_sub(cx, diag::RESTART_COMMUNICATIONS) {
        cx.push(
            "spec/app-6.8.1/01-restart-communications".into(),
            "FC 08/01 is echoed and the port keeps serving",
            format!("{APP}, section 6.8.1 (sub-function 01)"),
            "Restart Communications Option (data 00 00) outside listen only mode is answered with a normal response (an echo) before the restart, and the server answers requests after it.",
            vec![Tag::RtuOnly, Tag::Destructive],
            vec![
                exchange(
                    Outgoing::Pdu(diag_pdu(diag::RESTART_COMMUNICATIONS, 0)),
                    Compare::Exact,
                    "08/01 00 00",
                ),
                exchange(Outgoing::Pdu(read.clone()), Compare::Structure, "a read after the restart"),
            ],
        );
    }
    if declares_sub(cx, diag::FORCE_LISTEN_ONLY) && declares_sub(cx, diag::RESTART_COMMUNICATIONS) {
        cx.push(
            "spec/app-6.8.1/04-force-listen-only".into(),
            "FC 08/04 silences the port until 08/01",
            format!("{APP}, section 6.8.1 (sub-functions 04 and 01)"),
            "Force Listen Only Mode gets no response, and no request addressed to the server is answered until Restart Communications Option, which itself gets no response in listen only mode; afterwards the server answers again.",
            vec![Tag::RtuOnly, Tag::Destructive],
            vec![
                exchange(
                    Outgoing::Pdu(diag_pdu(diag::FORCE_LISTEN_ONLY, 0)),
                    Compare::Exact,
                    "08/04: no response",
                ),
                exchange(Outgoing::Pdu(read.clone()), Compare::Exact, "a read in listen only mode: no response"),
                exchange(
                    Outgoing::Pdu(diag_pdu(diag::RESTART_COMMUNICATIONS, 0)),
                    Compare::Exact,
                    "08/01 in listen only mode: no response, the port restarts",
                ),
                exchange(Outgoing::Pdu(read), Compare::Structure, "a read after the restart is answered"),
            ],
        );
    }
}

/// What comes before an FC 0B / FC 0C request in [`comm_event`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Prelude {
    /// Nothing: the counts and events are the drive's history, the format only is checked.
    None,
    /// 08/0A (Clear Counters and Diagnostic Register, spec 6.8.1), a successful read and two exception
    /// responses: FC 0B's count is then fixed by spec 6.9 (one completion; whether the clearing request counts
    /// is the freedom `event-counter-clear-counted`). The log is not cleared: FC 0C in format only.
    Clear,
    /// 08/01 with FF 00 (Restart Communications Option, clearing the log; serial line only, spec 6.8.1), a
    /// successful read and two exception responses: the count and the events are fixed by spec 6.9 and 6.10.
    Restart,
}

/// FC 0B (6.9) or FC 0C (6.10), after `prelude`. `None` when the profile lacks the function code, or the
/// FC 08 sub-function of the prelude.
pub fn comm_event(p: &Profile, unit: u8, fc: u8, prelude: Prelude) -> Option<Exercise> {
    let cx = Ctx::bare(p, unit);
    if !cx.supports(fc) || !matches!(fc, 0x0B | 0x0C) {
        return None;
    }
    let (sub, data, what) = match prelude {
        Prelude::None => {
            return Some(Exercise::plain(
                vec![fc],
                Compare::Structure,
                format!("FC {fc:02X}"),
            ));
        }
        Prelude::Clear => (diag::CLEAR_COUNTERS, 0, "08/0A: clear the counters"),
        Prelude::Restart => (
            diag::RESTART_COMMUNICATIONS,
            diag::RESTART_CLEAR_LOG,
            "08/01 FF 00: restart, clear the counters and the log",
        ),
    };
    if !cx.supports(FunctionCode::DIAGNOSTICS) || !declares_sub(&cx, sub) {
        return None;
    }
    let read = super::known_good_read(cx.p);
    let bad = exception_request(&cx);
    let mut e = Exercise::plain(
        vec![fc],
        if prelude == Prelude::Clear && fc == 0x0C {
            Compare::Structure
        } else {
            Compare::Exact
        },
        format!("FC {fc:02X}"),
    );
    e.before = vec![
        exchange(Outgoing::Pdu(diag_pdu(sub, data)), Compare::Exact, what),
        exchange(
            Outgoing::Pdu(read),
            Compare::Structure,
            "one successful read",
        ),
        exchange(
            Outgoing::Pdu(bad.clone()),
            Compare::Structure,
            "an exception response",
        ),
        exchange(
            Outgoing::Pdu(bad),
            Compare::Structure,
            "another exception response",
        ),
    ];
    match prelude {
        // 08/01 acts on a serial port (on Modbus/TCP it is not defined: exception 01 on the generic drive).
        Prelude::Restart => e.tags.push(Tag::RtuOnly),
        Prelude::Clear if fc == 0x0B => e.freedoms.push("event-counter-clear-counted".into()),
        _ => {}
    }
    Some(e)
}

/// FC 0B (6.9) and FC 0C (6.10). On a serial line the port is restarted first (08/01 with FF 00 clears the
/// counters, the event counter and the log, spec 6.8.1), so that the counts and the events that follow are
/// fixed by the spec: one successful read, two exception responses (not counted as completions), then FC
/// 0B, then FC 0C (its events the most recent first). Over Modbus/TCP the format only (the order of the
/// log's events on every transport: [`event_log_order`]).
fn comm_event_counter_and_log(cx: &mut Ctx) {
    for (fc, section, name) in [
        (0x0Bu8, "6.9", "get-comm-event-counter"),
        (0x0C, "6.10", "get-comm-event-log"),
    ] {
        if let Some(e) = comm_event(cx.p, cx.unit, fc, Prelude::Restart) {
            cx.push(
                format!("spec/app-{section}/{name}/after-restart"),
                format!("FC {fc:02X} after a restart, a read and two exceptions"),
                format!("{APP}, sections {section} and 6.8.1 (sub-function 01)"),
                if fc == 0x0B {
                    "The event counter counts each successful message completion, not exception responses nor FC 0B itself; a restart clears it."
                } else {
                    "The event log returns status, the event counter, the message count and the events, the most recent first; a restart with FF 00 clears the log and logs the restart."
                },
                vec![Tag::RtuOnly, Tag::Destructive],
                e.steps(),
            );
        }
        if fc == 0x0B
            && let Some(e) = comm_event(cx.p, cx.unit, fc, Prelude::Clear)
        {
            // Over Modbus/TCP the counter is cleared with 08/0A; whether the clearing request then counts as
            // a completion is the freedom `event-counter-clear-counted` (one more, never two).
            cx.push(
                format!("spec/app-{section}/{name}/after-clear"),
                "FC 0B after a clear, a read and two exceptions".to_string(),
                format!("{APP}, sections 6.9 and 6.8.1 (sub-function 0A)"),
                "The event counter counts each successful message completion, not exception responses nor FC 0B itself; Clear Counters and Diagnostic Register clears it.",
                vec![Tag::TcpOnly],
                e.steps(),
            );
        }
        if let Some(e) = comm_event(cx.p, cx.unit, fc, Prelude::None) {
            cx.push(
                format!("spec/app-{section}/{name}/format"),
                format!("FC {fc:02X}: the answer's format"),
                format!("{APP}, section {section}"),
                if fc == 0x0B {
                    "Get Comm Event Counter returns a 2-byte status and a 2-byte event count."
                } else {
                    "Get Comm Event Log returns a byte count, the status, the event count, the message count and 0-64 event bytes."
                },
                vec![Tag::TcpOnly],
                e.steps(),
            );
        }
    }
}

/// The most events two FC 0C reads with `between` requests between them can find entered (spec 6.10): a
/// receive event when each message arrives, a send event when its processing ends; no other event comes from
/// a read (04 and 00 come from 08/04 and 08/01). The first read's send event, the requests' two each, the
/// second read's receive event (whether a device logs it before it answers is its own).
pub fn event_log_max_new(between: usize) -> usize {
    1 + 2 * between + 1
}

/// FC 0C (6.10) without a known start state: the log read, a successful read and an exception response,
/// the log read again: the second log is the first with the new events in front and the oldest flushed
/// ([`crate::cases::Step::EventLogShifted`]). The read before the first log gives a short log an event
/// order that reads differently backwards. Which events and how many a device logs is not required: FC 0C is
/// a serial line function in the spec's table, and a device that serves it on Modbus/TCP as well may log no
/// Modbus/TCP traffic at all (an unchanged log passes); where it logs, the order is 6.10's. Any transport.
fn event_log_order(cx: &mut Ctx) {
    if !cx.supports(FunctionCode::GET_COMM_EVENT_LOG) {
        return;
    }
    let read = super::known_good_read(cx.p);
    let bad = exception_request(cx);
    let between = [
        exchange(
            Outgoing::Pdu(read.clone()),
            Compare::Structure,
            "a successful read",
        ),
        exchange(
            Outgoing::Pdu(bad),
            Compare::Structure,
            "an exception response",
        ),
    ];
    let max_new = event_log_max_new(between.len());
    let mut steps = vec![
        exchange(
            Outgoing::Pdu(read),
            Compare::Structure,
            "a successful read: events before the first log",
        ),
        capture(
            Outgoing::Pdu(vec![0x0C]),
            Compare::Structure,
            0,
            "FC 0C: the log before",
        ),
    ];
    steps.extend(between);
    steps.push(capture(
        Outgoing::Pdu(vec![0x0C]),
        Compare::Structure,
        1,
        "FC 0C: the log after",
    ));
    steps.push(Step::EventLogShifted {
        before: 0,
        after: 1,
        max_new,
        note: format!("the log after is the log before with at most {max_new} new events in front"),
    });
    cx.push(
        "spec/app-6.10/get-comm-event-log/new-events-in-front".to_string(),
        "FC 0C twice around two requests: new events in front, the oldest flushed",
        format!("{APP}, section 6.10"),
        "Byte 0 is the most recent event. Each new byte flushes the oldest byte from the field: a log read again after more requests is the first log with the new events (a receive and a send event per message at most) in front.",
        vec![],
        steps,
    );
}

/// FC 11 (6.13): exactly where the profile declares the server id and additional data, else in format; the
/// run indicator is either admissible value (0x00 OFF, 0xFF ON: the freedom `run-indicator-status`). `None`
/// without FC 11.
pub fn report_server_id(p: &Profile) -> Option<Exercise> {
    p.function(FunctionCode::REPORT_SERVER_ID)?;
    let mut e = Exercise::plain(
        vec![0x11],
        if p.server_id.is_some() {
            Compare::Exact
        } else {
            Compare::Structure
        },
        "FC 11",
    );
    e.freedoms.push("run-indicator-status".into());
    Some(e)
}

/// FC 11 (6.13): the server id, the run indicator (00 or FF) and the additional data the profile declares;
/// without a declaration, the format only.
fn report_server_id_case(cx: &mut Ctx) {
    let Some(e) = report_server_id(cx.p) else {
        return;
    };
    cx.push(
        "spec/app-6.13/report-server-id".into(),
        "FC 11 reports the server id and the run indicator",
        format!("{APP}, section 6.13"),
        "Report Server ID returns the device specific server id, the run indicator status (0x00 OFF, 0xFF ON) and device specific additional data.",
        vec![],
        e.steps(),
    );
}

/// The files of a profile: (number, records, writable).
pub fn files(p: &Profile) -> Vec<(u16, u16, bool)> {
    p.files
        .iter()
        .map(|f| f.get_ref())
        .map(|f| (f.number, f.records, f.access.writable()))
        .collect()
}

/// One group of file records (reference type 6, spec 6.14).
fn group(file: u16, record: u16, len: u16) -> FileRecordRef {
    FileRecordRef {
        reference_type: 6,
        file_number: file,
        record_number: record,
        record_length: len,
    }
}

/// FC 14 of `groups` (file, first record, number of records) in one request, exactly: the records hold what
/// the profile declares (0 where it declares nothing). `None` without FC 14.
pub fn read_file_records(p: &Profile, groups: &[(u16, u16, u16)]) -> Option<Exercise> {
    p.function(FunctionCode::READ_FILE_RECORD)?;
    let subs = groups.iter().map(|(f, r, n)| group(*f, *r, *n)).collect();
    let what = groups
        .iter()
        .map(|(f, r, n)| format!("file {f} records {r}..+{n}"))
        .collect::<Vec<_>>()
        .join(", ");
    Some(Exercise::plain(
        pdu(&Request::ReadFileRecord { sub_requests: subs }),
        Compare::Exact,
        format!("FC 14 of {what}"),
    ))
}

/// FC 15 of `groups` (file, first record, values) in one request: what the groups hold is read first (FC 14),
/// the request must be echoed, every group is read back, then put back. `None` without FC 14 and FC 15.
pub fn write_file_records(
    p: &Profile,
    unit: u8,
    groups: &[(u16, u16, Vec<u16>)],
) -> Option<Exercise> {
    let cx = Ctx::bare(p, unit);
    if !cx.supports(FunctionCode::WRITE_FILE_RECORD) || !cx.supports(FunctionCode::READ_FILE_RECORD)
    {
        return None;
    }
    let read = |file: u16, record: u16, len: usize| {
        Outgoing::Pdu(pdu(&Request::ReadFileRecord {
            sub_requests: vec![group(file, record, len as u16)],
        }))
    };
    let mut a = Around::new();
    let mut before = Vec::new();
    let mut undo = Vec::new();
    let mut read_back = Vec::new();
    for (file, record, values) in groups {
        let (file, record, len) = (*file, *record, values.len());
        let slot = a.slot();
        before.push(capture(
            read(file, record, len),
            Compare::Structure,
            slot,
            format!("read file {file} records {record}..+{len} first"),
        ));
        undo.push(exchange(
            Outgoing::RestoreRead { slot },
            Compare::Exact,
            format!("put back file {file} records {record}..+{len}"),
        ));
        read_back.push(exchange(
            read(file, record, len),
            Compare::Exact,
            format!("read back file {file} records {record}..+{len}"),
        ));
    }
    for s in before {
        a.set(s);
    }
    a.undo(undo);
    let write = Request::WriteFileRecord {
        sub_requests: groups
            .iter()
            .map(|(file, record, values)| FileRecordWrite {
                reference_type: 6,
                file_number: *file,
                record_number: *record,
                values: values.clone(),
            })
            .collect(),
    };
    Some(Exercise::around(
        a,
        pdu(&write),
        Compare::Exact,
        format!("FC 15, {} group(s): the request echoed", groups.len()),
        read_back,
    ))
}

/// FC 14 (6.14) and FC 15 (6.15) on the files the profile declares.
fn file_records(cx: &mut Ctx) {
    let files = files(cx.p);
    if files.is_empty() {
        return;
    }
    // Two groups, from the files with declared contents first, each from its first non-zero record, so
    // that the values read are the profile's, not zeros any drive would answer.
    let mut with_values: Vec<(u16, u16, u16)> =
        cx.p.files
            .iter()
            .map(|f| f.get_ref())
            .map(|f| {
                let start = f.values.iter().position(|v| *v != 0).unwrap_or(0) as u16;
                (f.number, start, f.records.saturating_sub(start).min(4))
            })
            .filter(|g| g.2 > 0)
            .collect();
    with_values.sort_by_key(|g| g.1 == 0);
    with_values.truncate(2);
    if let Some(e) = read_file_records(cx.p, &with_values) {
        cx.push(
            "spec/app-6.14/read-file-record".into(),
            format!("FC 14 reads {} groups of file records", with_values.len()),
            format!("{APP}, section 6.14; the profile's [[file]] tables"),
            "Read File Record returns one sub-response per group: its file response length (the reference type byte and the records), reference type 6 and the records' values.",
            vec![],
            e.steps(),
        );
    }
    let writable: Vec<(u16, u16)> = files
        .iter()
        .filter(|f| f.2 && f.1 >= 3)
        .map(|f| (f.0, f.1))
        .collect();
    let (Some(&(fa, _)), Some(&(fb, nb))) = (writable.first(), writable.last()) else {
        return;
    };
    // Two groups: records 1-2 of the first writable file and records 0-2 of the last one (the same file
    // when there is only one). What they hold is read first and written back after.
    let (ra, rb) = if fa == fb { (0, nb - 3) } else { (1, 0) };
    let groups = [
        (fa, ra, vec![0x06AF, 0x04BE]),
        (fb, rb, vec![0x100D, 0xA55A, 0x0001]),
    ];
    if let Some(e) = write_file_records(cx.p, cx.unit, &groups) {
        cx.push(
            "spec/app-6.15/write-file-record/read-back".into(),
            "FC 15 writes every group of a request (read back with FC 14)",
            format!("{APP}, sections 6.15 and 6.14; the profile's [[file]] tables"),
            "Write File Record writes every group of the request and returns an echo of the request; FC 14 reads the values written.",
            vec![Tag::Write],
            e.steps(),
        );
    }
}

/// The holding registers FC 16 can be tried on: one word wide, read and written, any 16-bit value in range,
/// neither motion nor destructive.
pub fn mask_registers(p: &Profile) -> Vec<u16> {
    p.registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| super::spec::settable(r, 0, 0xFFFF))
        .map(|r| r.address)
        .collect()
}

/// FC 16 (6.16) on the holding register at `address`: kept, set to `current`, masked (the request must be
/// echoed), read back, put back. `None` without FC 16 or a register write.
pub fn mask_write_register(
    p: &Profile,
    unit: u8,
    address: u16,
    current: u16,
    and_mask: u16,
    or_mask: u16,
) -> Option<Exercise> {
    let cx = Ctx::bare(p, unit);
    if !cx.supports(FunctionCode::MASK_WRITE_REGISTER) || !cx.can_write_registers() {
        return None;
    }
    let mut a = Around::new();
    a.keep_registers(&cx, address, 1);
    a.set(exchange(
        Outgoing::Pdu(pdu(&cx.write_request(address, vec![current]))),
        Compare::Exact,
        format!("current contents 0x{current:04X}"),
    ));
    // Spec 6.16: Result = (Current Contents AND And_Mask) OR (Or_Mask AND (NOT And_Mask)).
    let result = (current & and_mask) | (or_mask & !and_mask);
    Some(Exercise::around(
        a,
        pdu(&Request::MaskWriteRegister {
            address,
            and_mask,
            or_mask,
        }),
        Compare::Exact,
        format!("AND 0x{and_mask:04X}, OR 0x{or_mask:04X}: the request echoed"),
        vec![exchange(
            Outgoing::Pdu(pdu(&cx.read_request(address, 1, Table::Holding))),
            Compare::Exact,
            format!("read back: 0x{result:04X}"),
        )],
    ))
}

/// FC 16 (6.16): the spec's example on the first writable holding register, read back, then put back.
fn mask_write(cx: &mut Ctx) {
    let Some(&address) = mask_registers(cx.p).first() else {
        return;
    };
    let Some(e) = mask_write_register(cx.p, cx.unit, address, 0x0012, 0x00F2, 0x0025) else {
        return;
    };
    cx.push(
        format!("spec/app-6.16/mask-write/0x{address:04X}"),
        "FC 16 with the spec's example masks, read back",
        format!("{APP}, section 6.16"),
        "Mask Write Register sets the register to (current AND And_Mask) OR (Or_Mask AND (NOT And_Mask)) and echoes the request.",
        vec![Tag::Write],
        e.steps(),
    );
}

/// The queues of a profile: (pointer address, registers queued).
pub fn fifos(p: &Profile) -> Vec<(u16, usize)> {
    p.fifos
        .iter()
        .map(|f| f.get_ref())
        .map(|f| (f.address, f.values.len()))
        .collect()
}

/// FC 18 (6.18) of the queue at `address`, exactly: the queue holds what the profile declares. `None` without
/// FC 18.
pub fn read_fifo(p: &Profile, address: u16) -> Option<Exercise> {
    p.function(FunctionCode::READ_FIFO_QUEUE)?;
    Some(Exercise::plain(
        pdu(&Request::ReadFifoQueue { address }),
        Compare::Exact,
        format!("FC 18 of the queue at 0x{address:04X}"),
    ))
}

/// FC 18 (6.18): every queue the profile declares, read whole; a queue of more than 31 registers is
/// answered with exception 03.
fn fifo(cx: &mut Ctx) {
    for (address, n) in fifos(cx.p) {
        let Some(e) = read_fifo(cx.p, address) else {
            return;
        };
        let over = n > usize::from(codec::codes::MAX_FIFO_COUNT);
        cx.push(
            format!("spec/app-6.18/read-fifo-queue/0x{address:04X}"),
            format!("FC 18 reads the queue at 0x{address:04X} ({n} registers)"),
            format!("{APP}, section 6.18; the profile's [[fifo]] queues"),
            if over {
                "A queue of more than 31 registers is answered with exception 03 (Illegal Data Value)."
            } else {
                "Read FIFO Queue returns the byte count, the FIFO count and every queued register, the count first."
            },
            vec![],
            e.steps(),
        );
    }
}
