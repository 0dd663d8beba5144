//! The SD2x FC 43 fields "not used" (control bits 0-6, 004 line 608; the address offset, line 627): a drive
//! may leave them alone (`response`), and what the telegram then gets is the model's answer to it with the
//! field zero (`StepContext::choice_alternatives`), compared with the drive's as the step compares.

use codec::{CanOpenAccess, Request, Response};
use drives::choices::ModelledAlternative;
use drives::choices::ids::SD2X_FC43_OFFSET_NONZERO;
use drives::corpus::Corpus;
use engine::oracle::StepContext;
use engine::oracle::freedoms::alternatives;

/// A read of object 33 (DC voltage, 2 bytes) with the address offset `offset`.
fn read(offset: u16) -> CanOpenAccess {
    CanOpenAccess {
        control: 0,
        reserved: 0,
        node_id: 1,
        index: 33,
        subindex: 0,
        offset,
        byte_count: 2,
        data: Vec::new(),
    }
}

/// The answer to [`read`] with `offset` echoed and `data` read.
fn served(offset: u16, data: [u8; 2]) -> Response {
    Response::CanOpen(CanOpenAccess {
        data: data.to_vec(),
        ..read(offset)
    })
}

/// A well-formed step sending `req` to unit 1, the reference's answer decided by `decided`.
fn context<'a>(
    req: &'a Request,
    pdu: &'a [u8],
    p: &'a drives::profile::Profile,
    decided: &'a [drives::Decision],
    modelled: &'a [ModelledAlternative],
) -> StepContext<'a> {
    StepContext {
        request: Some(req),
        pdu,
        unit: 1,
        run_unit: 1,
        profile: p,
        malformed: false,
        batch: false,
        decided,
        counter_alternatives: &[],
        choice_alternatives: modelled,
        closed: false,
        short_of_length: false,
        gateway: false,
    }
}

/// The alternatives of `sd2x-fc43-offset-nonzero` for a read with offset 2 that the reference refused with
/// the offset's SDO error, the model having computed `modelled`, where the drive answered `observed`.
fn offset_alternatives(
    modelled: &[ModelledAlternative],
    observed: &Response,
) -> Vec<engine::oracle::freedoms::Alternative> {
    let reqs = Corpus::Embedded.requirements().expect("requirements");
    let p = Corpus::Embedded.profile("sd2x").expect("sd2x");
    let f = reqs.freedom(SD2X_FC43_OFFSET_NONZERO).expect("freedom");
    let req = Request::CanOpen(read(2));
    let pdu = req.to_bytes().expect("pdu");
    let decided = [SD2X_FC43_OFFSET_NONZERO];
    let cx = context(&req, &pdu, &p, &decided, modelled);
    let refused = Response::CanOpenError {
        sdo_code: 0xFFFF_0008,
    };
    alternatives(f, &cx, Some(&refused), Some(observed))
}

/// The model's answer with the offset zero is offered as `response`, with the offset the drive echoed, and
/// its values left for the step's comparison to judge (a voltage the drive measures differs from the
/// model's). Without the model's answer nothing admits the read served.
#[test]
fn a_drive_leaving_the_offset_alone_is_judged_by_the_models_answer() {
    let modelled = [(
        SD2X_FC43_OFFSET_NONZERO,
        "response",
        served(0, [0x10, 0x0E]),
    )];
    let observed = served(2, [0xE0, 0x15]);
    let alts = offset_alternatives(&modelled, &observed);
    let offered: Vec<_> = alts
        .iter()
        .filter(|a| a.shown.value == "response")
        .collect();
    assert_eq!(offered.len(), 1, "{alts:?}");
    assert_eq!(offered[0].answer, Some(served(2, [0x10, 0x0E])));
    // Served by a drive laying the offset out as the response layout prints it (0000h): the model's answer.
    let alts = offset_alternatives(&modelled, &served(0, [0xE0, 0x15]));
    assert!(
        alts.iter()
            .any(|a| a.answer == Some(served(0, [0x10, 0x0E])) && a.shown.value == "response"),
        "{alts:?}"
    );
    // Nothing the model computed: the read served is not admitted by this freedom.
    let alts = offset_alternatives(&[], &observed);
    assert!(
        !alts.iter().any(|a| a.shown.value == "response"),
        "{alts:?}"
    );
}

/// A reference leaving the offset alone (it followed the drive's `response`) answers with the offset as the
/// response layout prints it (0000h); a drive echoing the request's offset is admitted, its values compared
/// as the step compares. An offset the request did not carry is not.
#[test]
fn a_drive_echoing_the_offset_is_admitted_where_the_reference_left_it_alone() {
    let reference = served(0, [0x10, 0x0E]);
    let alts = offset_alternatives_after(&reference, &served(2, [0xE0, 0x15]));
    assert!(
        alts.iter()
            .any(|a| a.answer == Some(served(2, [0x10, 0x0E])) && a.shown.value == "response"),
        "{alts:?}"
    );
    let alts = offset_alternatives_after(&reference, &served(3, [0x10, 0x0E]));
    assert!(alts.is_empty(), "{alts:?}");
}

/// The alternatives of `sd2x-fc43-offset-nonzero` for a read with offset 2 that the reference served (`e`),
/// where the drive answered `observed`.
fn offset_alternatives_after(
    e: &Response,
    observed: &Response,
) -> Vec<engine::oracle::freedoms::Alternative> {
    let reqs = Corpus::Embedded.requirements().expect("requirements");
    let p = Corpus::Embedded.profile("sd2x").expect("sd2x");
    let f = reqs.freedom(SD2X_FC43_OFFSET_NONZERO).expect("freedom");
    let req = Request::CanOpen(read(2));
    let pdu = req.to_bytes().expect("pdu");
    let decided = [SD2X_FC43_OFFSET_NONZERO];
    let cx = context(&req, &pdu, &p, &decided, &[]);
    alternatives(f, &cx, Some(e), Some(observed))
}
