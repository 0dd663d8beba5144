//! Target URLs: `tcp://host:port`, `rtu+tcp://host:port[?gap=MS]`, `rtu:///dev/ttyX?baud=..&parity=..&stop=..&echo=..&byte_timeout=..`,
//! `sim:PROFILE`
//! (`PROFILE` a corpus profile's name or a profile file: `sim:./my.toml`, `sim:/abs/x.toml?transport=rtu`).

use std::fmt;

use codec::{CharFormat, Parity};

/// A parsed target address.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TargetUrl {
    /// Modbus/TCP.
    Tcp { host: String, port: u16 },
    /// RTU frames over a TCP connection (serial gateways, `simulate --rtu-over-tcp`). `gap_ms` (`?gap=MS`):
    /// the silence the device behind the connection needs to end a frame (a device server's or drive's own
    /// frame timeout), left after a frame it may still hold; `None`: twice the carrier's 50 ms.
    RtuOverTcp {
        host: String,
        port: u16,
        gap_ms: Option<u32>,
    },
    /// RTU on a serial device.
    Serial {
        path: String,
        baud: u32,
        format: CharFormat,
        /// The line gives back what the harness sends (`echo=on`: a two-wire RS-485 adapter that hears its
        /// own transmitter); each request's echo is checked and dropped before the answer is read.
        echo: bool,
        /// How long an answer the length rules say is incomplete waits for its next byte, in ms
        /// (`byte_timeout=MS`; `None`: [`super::serial::HOST_BYTE_TIMEOUT`]).
        byte_timeout_ms: Option<u32>,
    },
    /// The in-process reference drive of a profile (no sockets, virtual clock); `rtu` overrides the
    /// profile's native framing (`sim:generic?transport=rtu`). `profile` is a corpus name or a file path
    /// (see `drives::corpus::is_profile_path`).
    Sim { profile: String, rtu: Option<bool> },
}

/// Why a target URL was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "bad target `{url}`: {reason}\n  expected one of: tcp://HOST:PORT, rtu+tcp://HOST:PORT?gap=MS, rtu:///dev/ttyUSB0?baud=19200&parity=even&stop=1, sim:PROFILE, sim:PATH.toml"
)]
pub struct UrlError {
    pub url: String,
    pub reason: String,
}

fn host_port(url: &str, rest: &str) -> Result<(String, u16), UrlError> {
    let err = |reason: String| UrlError {
        url: url.to_string(),
        reason,
    };
    let rest = rest.trim_end_matches('/');
    if rest.is_empty() {
        return Err(err("no host".into()));
    }
    // [v6]:port, host:port, or host (port 502).
    let (host, port) = if let Some(r) = rest.strip_prefix('[') {
        let (h, after) = r
            .split_once(']')
            .ok_or_else(|| err("unclosed `[` in an IPv6 address".into()))?;
        match after.strip_prefix(':') {
            Some(p) => (h.to_string(), Some(p)),
            None if after.is_empty() => (h.to_string(), None),
            None => return Err(err(format!("unexpected `{after}` after the IPv6 address"))),
        }
    } else {
        match rest.rsplit_once(':') {
            Some((h, p)) if !h.contains(':') => (h.to_string(), Some(p)),
            Some(_) => {
                return Err(err(
                    "an IPv6 address must be written in brackets: tcp://[::1]:502".into(),
                ));
            }
            None => (rest.to_string(), None),
        }
    };
    if host.is_empty() {
        return Err(err("no host".into()));
    }
    let port = match port {
        None => 502,
        Some(p) => p
            .parse::<u16>()
            .ok()
            .filter(|p| *p != 0)
            .ok_or_else(|| err(format!("port `{p}` is not a number from 1 to 65535")))?,
    };
    Ok((host, port))
}

/// The `key=value` pairs of a URL's query (`a=1&b=2`), each checked to be one.
fn query_pairs(
    query: &str,
    err: impl Fn(String) -> UrlError,
) -> Result<Vec<(&str, &str)>, UrlError> {
    query
        .split('&')
        .filter(|s| !s.is_empty())
        .map(|kv| {
            kv.split_once('=')
                .ok_or_else(|| err(format!("`{kv}` is not key=value")))
        })
        .collect()
}

/// The value of option `key` as a number of milliseconds from 1 to 10,000; `what` says what it sets.
fn millis(
    key: &str,
    v: &str,
    what: &str,
    err: impl Fn(String) -> UrlError,
) -> Result<u32, UrlError> {
    v.parse::<u32>()
        .ok()
        .filter(|t| (1..=10_000).contains(t))
        .ok_or_else(|| {
            err(format!(
                "{key} `{v}` is not a number of milliseconds from 1 to 10000 ({what})"
            ))
        })
}

impl TargetUrl {
    /// Parse a target URL, naming precisely what is wrong.
    pub fn parse(url: &str) -> Result<Self, UrlError> {
        let err = |reason: String| UrlError {
            url: url.to_string(),
            reason,
        };
        if let Some(p) = url.strip_prefix("sim:") {
            let p = p.trim_start_matches("//");
            let (profile, query) = p.split_once('?').unwrap_or((p, ""));
            if profile.is_empty() {
                return Err(err(
                    "no profile after `sim:` (e.g. sim:sd2x, or a file: sim:./my.toml)".into(),
                ));
            }
            let rtu = match query {
                "" => None,
                "transport=rtu" => Some(true),
                "transport=tcp" => Some(false),
                q => {
                    return Err(err(format!(
                        "unknown sim option `{q}` (transport=rtu or transport=tcp)"
                    )));
                }
            };
            return Ok(TargetUrl::Sim {
                profile: profile.to_string(),
                rtu,
            });
        }
        if let Some(rest) = url.strip_prefix("tcp://") {
            let (host, port) = host_port(url, rest)?;
            return Ok(TargetUrl::Tcp { host, port });
        }
        if let Some(rest) = url.strip_prefix("rtu+tcp://") {
            let (rest, query) = rest.split_once('?').unwrap_or((rest, ""));
            let (host, port) = host_port(url, rest)?;
            let mut gap_ms = None;
            for (k, v) in query_pairs(query, err)? {
                match k {
                    "gap" => {
                        let what =
                            "the silence the device behind the connection needs to end a frame";
                        gap_ms = Some(millis(k, v, what, err)?);
                    }
                    _ => return Err(err(format!("unknown rtu+tcp option `{k}` (gap)"))),
                }
            }
            return Ok(TargetUrl::RtuOverTcp { host, port, gap_ms });
        }
        if let Some(rest) = url.strip_prefix("rtu://") {
            let (path, query) = rest.split_once('?').unwrap_or((rest, ""));
            if path.is_empty() || !path.starts_with('/') {
                return Err(err(
                    "the serial device must be an absolute path: rtu:///dev/ttyUSB0".into(),
                ));
            }
            let (mut baud, mut parity, mut stop, mut echo) = (19_200u32, Parity::Even, 1u8, false);
            let mut byte_timeout_ms = None;
            for (k, v) in query_pairs(query, err)? {
                match k {
                    "baud" => {
                        baud = v
                            .parse()
                            .ok()
                            .filter(|b| (50..=4_000_000).contains(b))
                            .ok_or_else(|| {
                                err(format!("baud `{v}` is not a rate from 50 to 4000000"))
                            })?
                    }
                    "parity" => {
                        parity = match v {
                            "none" | "n" | "N" => Parity::None,
                            "even" | "e" | "E" => Parity::Even,
                            "odd" | "o" | "O" => Parity::Odd,
                            _ => return Err(err(format!("parity `{v}` is not none, even or odd"))),
                        }
                    }
                    "stop" => {
                        stop = match v {
                            "1" => 1,
                            "2" => 2,
                            _ => return Err(err(format!("stop bits `{v}` is not 1 or 2"))),
                        }
                    }
                    "echo" => {
                        echo = match v {
                            "on" | "1" | "true" => true,
                            "off" | "0" | "false" => false,
                            _ => return Err(err(format!("echo `{v}` is not on or off"))),
                        }
                    }
                    "byte_timeout" => {
                        let what =
                            "how long an answer that is not complete waits for its next byte";
                        byte_timeout_ms = Some(millis(k, v, what, err)?);
                    }
                    _ => {
                        return Err(err(format!(
                            "unknown option `{k}` (baud, parity, stop, echo, byte_timeout)"
                        )));
                    }
                }
            }
            return Ok(TargetUrl::Serial {
                path: path.to_string(),
                baud,
                format: CharFormat {
                    parity,
                    stop_bits: stop,
                },
                echo,
                byte_timeout_ms,
            });
        }
        Err(err(match url.split_once("://") {
            Some((scheme, _)) => format!("unknown scheme `{scheme}`"),
            None => "no scheme".into(),
        }))
    }

    /// True for the in-process simulator (the safety policy does not apply to it).
    pub fn is_sim(&self) -> bool {
        matches!(self, TargetUrl::Sim { .. })
    }
}

impl fmt::Display for TargetUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TargetUrl::Tcp { host, port } if host.contains(':') => {
                write!(f, "tcp://[{host}]:{port}")
            }
            TargetUrl::Tcp { host, port } => write!(f, "tcp://{host}:{port}"),
            TargetUrl::RtuOverTcp { host, port, gap_ms } => {
                if host.contains(':') {
                    write!(f, "rtu+tcp://[{host}]:{port}")?;
                } else {
                    write!(f, "rtu+tcp://{host}:{port}")?;
                }
                match gap_ms {
                    Some(g) => write!(f, "?gap={g}"),
                    None => Ok(()),
                }
            }
            TargetUrl::Serial {
                path,
                baud,
                format,
                echo,
                byte_timeout_ms,
            } => {
                let p = match format.parity {
                    Parity::None => "none",
                    Parity::Even => "even",
                    Parity::Odd => "odd",
                };
                write!(
                    f,
                    "rtu://{path}?baud={baud}&parity={p}&stop={}{}",
                    format.stop_bits,
                    if *echo { "&echo=on" } else { "" }
                )?;
                match byte_timeout_ms {
                    Some(t) => write!(f, "&byte_timeout={t}"),
                    None => Ok(()),
                }
            }
            TargetUrl::Sim { profile, rtu: None } => write!(f, "sim:{profile}"),
            TargetUrl::Sim {
                profile,
                rtu: Some(r),
            } => {
                write!(
                    f,
                    "sim:{profile}?transport={}",
                    if *r { "rtu" } else { "tcp" }
                )
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::TargetUrl;

    /// `url` parses as `want`, and prints as something that parses the same.
    fn parses_and_prints(url: &str, want: &TargetUrl) {
        let got = TargetUrl::parse(url).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&got, want, "{url}");
        assert_eq!(
            TargetUrl::parse(&got.to_string()).as_ref(),
            Ok(&got),
            "{url} prints as it parses"
        );
    }

    #[test]
    fn sim_targets_take_a_profile_name_or_a_file() {
        let sim = |profile: &str, rtu| TargetUrl::Sim {
            profile: profile.into(),
            rtu,
        };
        for (url, want) in [
            ("sim:sd2x", sim("sd2x", None)),
            ("sim:./my.toml", sim("./my.toml", None)),
            ("sim:my.toml", sim("my.toml", None)),
            (
                "sim:/abs/x.toml?transport=rtu",
                sim("/abs/x.toml", Some(true)),
            ),
            (
                "sim:../d/x.toml?transport=tcp",
                sim("../d/x.toml", Some(false)),
            ),
            ("sim:///abs/x.toml", sim("/abs/x.toml", None)),
        ] {
            parses_and_prints(url, &want);
        }
        let e = TargetUrl::parse("sim:").unwrap_err();
        assert!(e.reason.contains("sim:./my.toml"), "{e}");
        let e = TargetUrl::parse("sim:./my.toml?baud=9600").unwrap_err();
        assert!(e.reason.contains("unknown sim option `baud=9600`"), "{e}");
    }

    #[test]
    fn serial_targets_take_line_settings_and_the_local_echo() {
        use codec::{CharFormat, Parity};
        let got = TargetUrl::parse("rtu:///dev/ttyUSB0?baud=9600&parity=none&stop=2&echo=on")
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            got,
            TargetUrl::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 9600,
                format: CharFormat {
                    parity: Parity::None,
                    stop_bits: 2
                },
                echo: true,
                byte_timeout_ms: None,
            }
        );
        assert_eq!(TargetUrl::parse(&got.to_string()).as_ref(), Ok(&got));
        let plain = TargetUrl::parse("rtu:///dev/ttyUSB0").unwrap_or_else(|e| panic!("{e}"));
        assert!(matches!(plain, TargetUrl::Serial { echo: false, .. }));
        assert!(!plain.to_string().contains("echo"), "{plain}");
        let e = TargetUrl::parse("rtu:///dev/ttyUSB0?echo=maybe").unwrap_err();
        assert!(e.reason.contains("echo `maybe` is not on or off"), "{e}");
        let e = TargetUrl::parse("rtu:///dev/ttyUSB0?loopback=1").unwrap_err();
        assert!(
            e.reason
                .contains("(baud, parity, stop, echo, byte_timeout)"),
            "{e}"
        );
        let slow = TargetUrl::parse("rtu:///dev/ttyUSB0?byte_timeout=64")
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(matches!(
            slow,
            TargetUrl::Serial {
                byte_timeout_ms: Some(64),
                ..
            }
        ));
        assert_eq!(TargetUrl::parse(&slow.to_string()).as_ref(), Ok(&slow));
        let e = TargetUrl::parse("rtu:///dev/ttyUSB0?byte_timeout=0").unwrap_err();
        assert!(e.reason.contains("byte_timeout `0` is not a number"), "{e}");
    }

    #[test]
    fn rtu_over_tcp_targets_take_the_devices_frame_gap() {
        let rtu_tcp = |host: &str, port, gap_ms| TargetUrl::RtuOverTcp {
            host: host.into(),
            port,
            gap_ms,
        };
        for (url, want) in [
            ("rtu+tcp://127.0.0.1:4001", rtu_tcp("127.0.0.1", 4001, None)),
            (
                "rtu+tcp://127.0.0.1:4001?gap=250",
                rtu_tcp("127.0.0.1", 4001, Some(250)),
            ),
            ("rtu+tcp://[::1]?gap=20", rtu_tcp("::1", 502, Some(20))),
            (
                "rtu+tcp://localhost/?gap=5",
                rtu_tcp("localhost", 502, Some(5)),
            ),
        ] {
            parses_and_prints(url, &want);
        }
        for (url, says) in [
            ("rtu+tcp://127.0.0.1:4001?gap=0", "gap `0` is not a number"),
            (
                "rtu+tcp://127.0.0.1:4001?gap=2s",
                "gap `2s` is not a number",
            ),
            ("rtu+tcp://127.0.0.1:4001?gap", "`gap` is not key=value"),
            (
                "rtu+tcp://127.0.0.1:4001?baud=9600",
                "unknown rtu+tcp option `baud` (gap)",
            ),
            ("rtu+tcp://?gap=5", "no host"),
        ] {
            let e = TargetUrl::parse(url).unwrap_err();
            assert!(e.reason.contains(says), "{url}: {e}");
        }
    }
}
