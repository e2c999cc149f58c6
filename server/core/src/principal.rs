//! Who calls: every session belongs to the principal that created it, and every call on a session
//! names its caller. A caller that is neither the owner nor an admin is told the session does not
//! exist (NOT_FOUND, the same answer as for an id never created), so ids cannot be probed.
//!
//! The transport decides who the caller is (a bearer token, or nobody when authentication is off:
//! then every caller is [`Principal::local`], an admin). Per-principal limits apply on top of the
//! server-wide ones in [`crate::Limits`].

use std::sync::Arc;

use serde::{Deserialize, Serialize};

/// Limits of one principal, on top of the server's. `None`: only the server's limit applies.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PrincipalLimits {
    /// Sessions open at once.
    pub max_sessions: Option<usize>,
    /// Environments across the principal's sessions.
    pub max_envs: Option<usize>,
    /// Bytes the principal's sessions, buffers, streams and channels may reserve together.
    pub memory_bytes: Option<u64>,
}

/// What a principal may do.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Creates sessions and uses its own.
    #[default]
    User,
    /// Sees every session (ListSessions, DescribeSession, ListEnvs) and changes nothing: dashboards,
    /// probes that look deeper than health.
    Monitor,
    /// Everything, on every principal's sessions: list, describe, use and close them.
    Admin,
}

/// An authenticated caller.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Principal {
    name: Arc<str>,
    role: Role,
    limits: PrincipalLimits,
}

impl Principal {
    pub fn new(name: &str, role: Role, limits: PrincipalLimits) -> Principal {
        Principal { name: name.into(), role, limits }
    }

    /// The caller when authentication is off (a server on loopback): one admin with no limits of
    /// its own.
    pub fn local() -> Principal {
        Principal::new("local", Role::Admin, PrincipalLimits::default())
    }

    pub fn role(&self) -> Role {
        self.role
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub(crate) fn shared_name(&self) -> Arc<str> {
        self.name.clone()
    }

    /// Admins may see, use and close every principal's sessions.
    pub fn is_admin(&self) -> bool {
        self.role == Role::Admin
    }

    pub fn limits(&self) -> &PrincipalLimits {
        &self.limits
    }

    /// Whether this caller may act on a session owned by `owner`.
    pub fn may_use(&self, owner: &str) -> bool {
        self.is_admin() || *self.name == *owner
    }

    /// Whether this caller may see a session owned by `owner` (list and describe it).
    pub fn may_see(&self, owner: &str) -> bool {
        self.role == Role::Monitor || self.may_use(owner)
    }
}

/// The part of a session id that identifies it in logs without being usable: its counter
/// (`s12-9f...` logs as `s12`). The rest of the id is not a secret (sessions are checked against
/// their owner) but it is what a client passes, and logs are read by more people than own sessions.
pub fn log_id(session_id: &str) -> &str {
    session_id.split_once('-').map_or(session_id, |(counter, _)| counter)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn owners_and_admins_may_use_a_session_and_no_one_else() {
        let alice = Principal::new("alice", Role::User, PrincipalLimits::default());
        let root = Principal::new("ops", Role::Admin, PrincipalLimits::default());
        let dashboard = Principal::new("dashboard", Role::Monitor, PrincipalLimits::default());
        assert!(alice.may_use("alice"));
        assert!(!alice.may_use("bob") && !alice.may_see("bob"));
        assert!(!alice.may_use("alic"));
        assert!(root.may_use("bob"));
        assert!(dashboard.may_see("bob") && !dashboard.may_use("bob"));
    }

    #[test]
    fn logs_show_the_counter_only() {
        assert_eq!(log_id("s12-0123456789abcdef"), "s12");
        assert_eq!(log_id("odd"), "odd");
    }
}
