//! Where the DDS participant looks for peers, from ROS 2's discovery variables (Iron and
//! later): `ROS_DOMAIN_ID`, `ROS_AUTOMATIC_DISCOVERY_RANGE` and `ROS_STATIC_PEERS`.
//!
//! rustdds always announces itself by unicast to the well-known discovery ports of this
//! host as well as by multicast, so peers on the same host meet with no multicast at all
//! (a loopback without the MULTICAST flag). A static peer on another host cannot be given
//! to rustdds 0.15: such peers are reported, and found only if multicast reaches them.

use ros2_client::dds::rustdds::{DomainParticipant, DomainParticipantBuilder};
use std::net::{IpAddr, Ipv4Addr, ToSocketAddrs};

/// `ROS_AUTOMATIC_DISCOVERY_RANGE`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Range {
    /// `SUBNET`, `SYSTEM_DEFAULT` or unset: multicast on every interface, and this host.
    Subnet,
    /// `LOCALHOST`: this host only (loopback).
    Localhost,
    /// `OFF`: no automatic discovery; only `ROS_STATIC_PEERS`.
    Off,
}

/// The discovery settings of one participant.
#[derive(Clone, Debug, PartialEq)]
pub struct Discovery {
    pub domain_id: u16,
    pub range: Range,
    /// `ROS_STATIC_PEERS`, as given (`;`-separated hosts or addresses).
    pub static_peers: Vec<String>,
}

/// A discovery variable with a value ROS 2 does not accept.
#[derive(Clone, Debug, PartialEq)]
pub struct BadVariable {
    pub name: &'static str,
    pub value: String,
    pub expected: &'static str,
}

impl std::fmt::Display for BadVariable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}='{}': expected {}",
            self.name, self.value, self.expected
        )
    }
}

impl std::error::Error for BadVariable {}

/// Highest domain id whose ports fit in 16 bits (RTPS: 7400 + 250 d + ...).
const MAX_DOMAIN_ID: u16 = 232;

impl Discovery {
    /// From this process's environment.
    pub fn from_env() -> Result<Self, BadVariable> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// From variables looked up by `var` (an unset or empty variable is its default).
    pub fn from_vars(var: impl Fn(&str) -> Option<String>) -> Result<Self, BadVariable> {
        let get = |k: &str| {
            var(k)
                .map(|v| v.trim().to_string())
                .filter(|v| !v.is_empty())
        };
        let domain_id = match get("ROS_DOMAIN_ID") {
            None => 0,
            Some(v) => v
                .parse::<u16>()
                .ok()
                .filter(|d| *d <= MAX_DOMAIN_ID)
                .ok_or(BadVariable {
                    name: "ROS_DOMAIN_ID",
                    value: v,
                    expected: "an integer from 0 to 232",
                })?,
        };
        let range = match get("ROS_AUTOMATIC_DISCOVERY_RANGE").as_deref() {
            None | Some("SUBNET") | Some("SYSTEM_DEFAULT") => Range::Subnet,
            Some("LOCALHOST") => Range::Localhost,
            Some("OFF") => Range::Off,
            Some(v) => {
                return Err(BadVariable {
                    name: "ROS_AUTOMATIC_DISCOVERY_RANGE",
                    value: v.to_string(),
                    expected: "SUBNET, LOCALHOST, OFF or SYSTEM_DEFAULT",
                })
            }
        };
        let static_peers = get("ROS_STATIC_PEERS")
            .map(|v| {
                v.split(';')
                    .map(str::trim)
                    .filter(|p| !p.is_empty())
                    .map(String::from)
                    .collect()
            })
            .unwrap_or_default();
        Ok(Self {
            domain_id,
            range,
            static_peers,
        })
    }

    /// Static peers that are not this host: rustdds cannot reach them by unicast.
    pub fn remote_static_peers(&self) -> Vec<String> {
        self.static_peers
            .iter()
            .filter(|p| !is_this_host(p))
            .cloned()
            .collect()
    }

    /// A participant that discovers as these settings say.
    pub fn participant(&self) -> Result<DomainParticipant, String> {
        let b = DomainParticipantBuilder::new(self.domain_id);
        let b = match self.range {
            Range::Subnet => b,
            // Multicast and advertised locators on loopback only; same-host unicast
            // discovery (on by default) finds the peers.
            Range::Localhost | Range::Off => {
                b.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)])
            }
        };
        b.build().map_err(|e| {
            format!(
                "creating the DDS participant (domain {}): {e}",
                self.domain_id
            )
        })
    }

    /// One line for the service's start-up log.
    pub fn describe(&self) -> String {
        let range = match self.range {
            Range::Subnet => "subnet",
            Range::Localhost => "localhost",
            Range::Off => "off",
        };
        let mut s = format!("ROS 2 domain {}, discovery range {range}", self.domain_id);
        if !self.static_peers.is_empty() {
            s += &format!(", static peers {}", self.static_peers.join(";"));
        }
        s
    }
}

/// A loopback address, or a name that resolves only to this host's loopback.
fn is_this_host(peer: &str) -> bool {
    if let Ok(ip) = peer.parse::<IpAddr>() {
        return ip.is_loopback();
    }
    if peer.eq_ignore_ascii_case("localhost") {
        return true;
    }
    match (peer, 0).to_socket_addrs() {
        Ok(addrs) => {
            let addrs: Vec<_> = addrs.collect();
            !addrs.is_empty() && addrs.iter().all(|a| a.ip().is_loopback())
        }
        Err(_) => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn from(vars: &[(&str, &str)]) -> Result<Discovery, BadVariable> {
        let m: HashMap<String, String> = vars
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        Discovery::from_vars(|k| m.get(k).cloned())
    }

    #[test]
    fn unset_variables_are_ros_defaults() {
        let d = from(&[]).unwrap();
        assert_eq!(
            (d.domain_id, d.range, d.static_peers.len()),
            (0, Range::Subnet, 0)
        );
    }

    #[test]
    fn variables_are_read_as_ros_spells_them() {
        let d = from(&[
            ("ROS_DOMAIN_ID", "42"),
            ("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"),
            ("ROS_STATIC_PEERS", "127.0.0.1; localhost;192.0.2.7;"),
        ])
        .unwrap();
        assert_eq!(d.domain_id, 42);
        assert_eq!(d.range, Range::Localhost);
        assert_eq!(d.static_peers, ["127.0.0.1", "localhost", "192.0.2.7"]);
        assert_eq!(d.remote_static_peers(), ["192.0.2.7"]);
        assert_eq!(
            from(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")])
                .unwrap()
                .range,
            Range::Off
        );
    }

    #[test]
    fn bad_values_are_errors_that_name_the_variable() {
        for (k, v) in [
            ("ROS_DOMAIN_ID", "233"),
            ("ROS_DOMAIN_ID", "-1"),
            ("ROS_DOMAIN_ID", "one"),
            ("ROS_AUTOMATIC_DISCOVERY_RANGE", "lan"),
        ] {
            let e = from(&[(k, v)]).unwrap_err();
            assert_eq!(e.name, k);
            assert!(e.to_string().contains(v), "{e}");
        }
    }
}
