//! The Ivy bus address: `IVYBUS` and `-b`/`--ivy-bus` strings, as Paparazzi's tools take them.
//!
//! Syntax (ivy-c `ivysocket.c`/`ivy.c` `IvyStart`, ivy-python `ivy.py` `decode_ivybus`):
//! `[DOMAIN[,DOMAIN]...][:PORT]`. A domain is a dotted IPv4 address; a short one is
//! completed with `255`s into a broadcast address (`127` → `127.255.255.255`,
//! `10.192.33` → `10.192.33.255`). An empty domain list means `127.255.255.255`, a missing
//! port 2010: Paparazzi's defaults on Linux. Multicast domains (224.0.0.0/4) are accepted too.

use std::net::Ipv4Addr;

/// The default bus, as in Paparazzi on Linux.
pub const DEFAULT_BUS: &str = "127.255.255.255:2010";

/// The default UDP port.
pub const DEFAULT_PORT: u16 = 2010;

/// A parsed bus address.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BusAddr {
    /// Where hellos are sent (and, for a single loopback domain, received).
    pub domains: Vec<Ipv4Addr>,
    /// The UDP port.
    pub port: u16,
}

/// A bus string that does not parse.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("bad Ivy bus {text:?}: {why} (expected DOMAIN[,DOMAIN]...[:PORT], e.g. 127.255.255.255:2010)")]
pub struct BusAddrError {
    /// The string.
    pub text: String,
    /// What is wrong.
    pub why: String,
}

impl BusAddr {
    /// Parses `text` (see the module docs).
    pub fn parse(text: &str) -> Result<BusAddr, BusAddrError> {
        let err = |why: String| BusAddrError { text: text.chars().take(100).collect(), why };
        let t = text.trim();
        let (domains, port) = match t.rsplit_once(':') {
            Some((d, p)) => {
                let port = p.parse::<u16>().map_err(|_| err(format!("port `{p}` is not a number in 1..65535")))?;
                if port == 0 {
                    return Err(err("port 0".into()));
                }
                (d, port)
            }
            None => (t, DEFAULT_PORT),
        };
        let mut out = Vec::new();
        for d in domains.split(',').map(str::trim).filter(|d| !d.is_empty()) {
            out.push(parse_domain(d).ok_or_else(|| err(format!("domain `{d}` is not an IPv4 address or prefix")))?);
        }
        if out.is_empty() {
            out.push(Ipv4Addr::new(127, 255, 255, 255));
        }
        Ok(BusAddr { domains: out, port })
    }

    /// `IVYBUS` if set and not empty, else [`DEFAULT_BUS`]; `explicit` (a command-line option)
    /// wins over both.
    pub fn from_env_or(explicit: Option<&str>) -> Result<BusAddr, BusAddrError> {
        if let Some(e) = explicit {
            return BusAddr::parse(e);
        }
        match std::env::var("IVYBUS") {
            Ok(v) if !v.trim().is_empty() => BusAddr::parse(&v),
            _ => BusAddr::parse(DEFAULT_BUS),
        }
    }

    /// Whether every domain is on the loopback network (127.0.0.0/8).
    pub fn is_loopback(&self) -> bool {
        self.domains.iter().all(Ipv4Addr::is_loopback)
    }
}

impl std::fmt::Display for BusAddr {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let d: Vec<String> = self.domains.iter().map(ToString::to_string).collect();
        write!(f, "{}:{}", d.join(","), self.port)
    }
}

fn parse_domain(d: &str) -> Option<Ipv4Addr> {
    let parts: Vec<&str> = d.split('.').collect();
    if parts.is_empty() || parts.len() > 4 {
        return None;
    }
    let mut octets = [255u8; 4];
    for (o, p) in octets.iter_mut().zip(&parts) {
        *o = p.parse().ok()?;
    }
    Some(Ipv4Addr::from(octets))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_paparazzi_bus_strings() {
        let lo = Ipv4Addr::new(127, 255, 255, 255);
        assert_eq!(BusAddr::parse(DEFAULT_BUS).unwrap(), BusAddr { domains: vec![lo], port: 2010 });
        assert_eq!(BusAddr::parse("127:2011").unwrap(), BusAddr { domains: vec![lo], port: 2011 });
        assert_eq!(BusAddr::parse(":3000").unwrap(), BusAddr { domains: vec![lo], port: 3000 });
        assert_eq!(BusAddr::parse("").unwrap(), BusAddr { domains: vec![lo], port: 2010 });
        assert_eq!(
            BusAddr::parse("10.192.33,127.0.0.1:2010").unwrap().domains,
            [Ipv4Addr::new(10, 192, 33, 255), Ipv4Addr::new(127, 0, 0, 1)]
        );
        assert!(BusAddr::parse("127:2010").unwrap().is_loopback());
        assert!(!BusAddr::parse("10.1:2010").unwrap().is_loopback());
        assert_eq!(BusAddr::parse("127.255.255.255:2010").unwrap().to_string(), DEFAULT_BUS);
        for bad in ["127:x", "127:0", "127:70000", "1.2.3.4.5:10", "a.b:10", "300:10"] {
            let e = BusAddr::parse(bad).unwrap_err();
            assert!(e.to_string().contains(bad), "{e}");
        }
    }
}
