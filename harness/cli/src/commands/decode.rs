//! `modbus-harness decode`: the tool a user reaches for when a drive sends something odd.

use crate::exit::Exit;
use std::process::ExitCode;

use clap::Args;
use codec::{
    DecodeErrorKind, Direction, Framing, Lenient, Pdu, describe, hex_spaced, parse_hex, rtu, tcp,
};

/// Arguments of `decode`.
#[derive(Args)]
#[command(group(clap::ArgGroup::new("framing").required(true).args(["tcp", "rtu", "pdu"])))]
pub struct DecodeArgs {
    /// The bytes are a Modbus/TCP ADU (MBAP header + PDU).
    #[arg(long)]
    tcp: bool,
    /// The bytes are an RTU ADU (address + PDU + CRC), also for RTU over TCP.
    #[arg(long)]
    rtu: bool,
    /// The bytes are a bare PDU (function code + data), as the TCP manuals print them.
    #[arg(long)]
    pdu: bool,
    /// Decode as a response (default: request).
    #[arg(long)]
    response: bool,
    /// The frame in hex; spaces, 0x prefixes and : , - separators are allowed. `-` reads standard input.
    hex: Vec<String>,
}

/// Run `decode`: exit 0 when the frame decodes strictly, 1 when it does not, 2 on unusable input.
pub fn run(args: &DecodeArgs) -> ExitCode {
    let text = if args.hex.len() == 1 && args.hex[0] == "-" {
        let mut s = String::new();
        if let Err(e) = std::io::Read::read_to_string(&mut std::io::stdin(), &mut s) {
            eprintln!("error: reading standard input: {e}");
            return ExitCode::from(Exit::Unusable);
        }
        s
    } else {
        args.hex.join(" ")
    };
    let bytes = match parse_hex(&text) {
        Ok(b) if !b.is_empty() => b,
        Ok(_) => {
            eprintln!("error: no bytes given (pass the frame as hex, e.g. 010307D000018487)");
            return ExitCode::from(Exit::Unusable);
        }
        Err(e) => {
            eprintln!("error: not hex: {e} (input: {text:?})");
            return ExitCode::from(Exit::Unusable);
        }
    };
    let framing = if args.tcp {
        Framing::Tcp
    } else if args.rtu {
        Framing::Rtu
    } else {
        Framing::Pdu
    };
    let dir = if args.response {
        Direction::Response
    } else {
        Direction::Request
    };
    print!("{}", render(&bytes, framing, dir));
    if Lenient::decode(&bytes, framing, dir).is_valid() {
        ExitCode::from(Exit::Ok)
    } else {
        ExitCode::from(Exit::Failed)
    }
}

fn row(out: &mut String, name: &str, value: impl std::fmt::Display) {
    out.push_str(&format!("  {name:<16} {value}\n"));
}

/// The field-by-field rendering; on a strict error, what can be read leniently and then the exact error.
pub fn render(bytes: &[u8], framing: Framing, dir: Direction) -> String {
    let mut out = String::new();
    let what = match (framing, dir) {
        (Framing::Tcp, Direction::Request) => "Modbus/TCP request",
        (Framing::Tcp, Direction::Response) => "Modbus/TCP response",
        (Framing::Rtu, Direction::Request) => "RTU request",
        (Framing::Rtu, Direction::Response) => "RTU response",
        (Framing::Pdu, Direction::Request) => "request PDU",
        (Framing::Pdu, Direction::Response) => "response PDU",
    };
    out.push_str(&format!(
        "{what}, {} bytes: {}\n",
        bytes.len(),
        hex_spaced(bytes)
    ));
    let lenient = Lenient::decode(bytes, framing, dir);
    // The PDU bytes as framing delimits them, checked or not, so a bad CRC still shows what was meant.
    let (pdu_bytes, pdu_base): (&[u8], usize) = match framing {
        Framing::Tcp => {
            if let Some(h) = tcp::Mbap::parse(bytes) {
                row(
                    &mut out,
                    "transaction id",
                    format!("{} (0x{:04X})", h.transaction_id, h.transaction_id),
                );
                let pid_note = if h.protocol_id == 0 {
                    ""
                } else {
                    "  <- must be 0"
                };
                row(
                    &mut out,
                    "protocol id",
                    format!("0x{:04X}{pid_note}", h.protocol_id),
                );
                let actual = bytes.len() - 6;
                let len_note = if h.length as usize == actual {
                    String::new()
                } else {
                    format!("  <- the frame carries {actual}")
                };
                row(&mut out, "length", format!("{}{len_note}", h.length));
                row(
                    &mut out,
                    "unit id",
                    format!("{} (0x{:02X})", h.unit_id, h.unit_id),
                );
                (&bytes[tcp::MBAP_LEN..], tcp::MBAP_LEN)
            } else {
                (&[][..], 0)
            }
        }
        Framing::Rtu => {
            if bytes.len() >= 3 {
                row(
                    &mut out,
                    "slave address",
                    format!(
                        "{} (0x{:02X}){}",
                        bytes[0],
                        bytes[0],
                        if bytes[0] == 0 { " broadcast" } else { "" }
                    ),
                );
                (&bytes[1..bytes.len() - 2], 1)
            } else {
                (&[][..], 0)
            }
        }
        Framing::Pdu => (bytes, 0),
    };
    let pdu = Pdu::decode(pdu_bytes, dir);
    match &pdu {
        Ok(p) => {
            for f in describe(p) {
                if f.name == "function" {
                    let fc = codec::FunctionCode(pdu_bytes[0]);
                    row(&mut out, "function", fc);
                } else if f.name == "exception" {
                    row(
                        &mut out,
                        "exception",
                        codec::ExceptionCode(match f.value {
                            codec::FieldValue::Int(v) => v as u8,
                            _ => 0,
                        }),
                    );
                } else {
                    row(&mut out, f.name, &f.value);
                }
            }
        }
        Err(_) if !pdu_bytes.is_empty() => {
            row(&mut out, "function", codec::FunctionCode(pdu_bytes[0]));
            row(&mut out, "data", hex_spaced(&pdu_bytes[1..]));
        }
        Err(_) => {}
    }
    if framing == Framing::Rtu && bytes.len() >= 3 {
        let (body, c) = bytes.split_at(bytes.len() - 2);
        let received = u16::from_le_bytes([c[0], c[1]]);
        let expected = rtu::crc16(body);
        if expected == received {
            row(
                &mut out,
                "CRC",
                format!("0x{received:04X} (bytes {:02X} {:02X}) OK", c[0], c[1]),
            );
        } else {
            row(
                &mut out,
                "CRC",
                format!(
                    "0x{received:04X} received (bytes {:02X} {:02X}), expected 0x{expected:04X} (bytes {:02X} {:02X})  <- MISMATCH",
                    c[0],
                    c[1],
                    expected & 0xFF,
                    expected >> 8
                ),
            );
        }
    }
    match &lenient.result {
        Ok(_) => out.push_str("OK: decodes strictly\n"),
        Err(e) => {
            // A PDU error found after a good ADU check is reported at the right ADU offset already.
            let _ = pdu_base;
            let hint = match &e.kind {
                DecodeErrorKind::Crc { .. } => {
                    " (the frame was corrupted, or the sender computes the CRC wrongly)"
                }
                _ => "",
            };
            out.push_str(&format!("error: {e}{hint}\n"));
        }
    }
    out
}
