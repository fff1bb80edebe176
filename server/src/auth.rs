//! Authentication and authorization (`--auth FILE`).
//!
//! The auth file (JSON, format 1; docs/service.md, "Authentication") lists principals. Each has
//! the SHA-256 hashes of its bearer tokens (the tokens themselves are never stored), optionally
//! the subjects of client certificates (mTLS) that stand for it, the cases it may use (exact ids,
//! or prefixes ending in `*`: a tenant), its roles and its session quota:
//!
//! ```json
//! {"format": 1, "open_health": true, "open_reflection": true,
//!  "principals": [{"principal": "or1-navigation", "token_sha256": ["9f86d0…"],
//!                  "certificate_subjects": ["CN=or1-navigation"],
//!                  "cases": ["hospital-a/*"], "roles": ["register"], "max_sessions": 2}]}
//! ```
//!
//! A call authenticates with `authorization: Bearer TOKEN`, or (no such header) with a client
//! certificate whose subject is listed. Roles: `read` lists and describes cases; `register`
//! registers (and reads); `manage` uploads and deletes cases (and reads). A token that is absent
//! or unknown: UNAUTHENTICATED; a missing role: PERMISSION_DENIED; a case the principal may not
//! use: NOT_FOUND, worded exactly as for a case that does not exist.

use crate::error::{PermissionDenied, ServiceError, Unauthenticated};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::sync::Arc;

/// A role a principal may hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// List and describe cases.
    Read,
    /// Register (unary and streamed); implies `read`.
    Register,
    /// Upload and delete cases; implies `read`.
    Manage,
}

impl Role {
    /// The role's name in the auth file.
    pub fn name(self) -> &'static str {
        match self {
            Role::Read => "read",
            Role::Register => "register",
            Role::Manage => "manage",
        }
    }
}

/// One principal of the auth file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrincipalEntry {
    /// The principal's name (logged and audited).
    pub principal: String,
    /// SHA-256 of each token, 64 hex digits (`librplus-server token` makes a token and its hash).
    #[serde(default)]
    pub token_sha256: Vec<String>,
    /// Client-certificate subjects that authenticate as this principal: the whole subject as
    /// RFC 4514 writes it (`CN=nav, O=Hospital A`), or its common name alone (`CN=nav`).
    #[serde(default)]
    pub certificate_subjects: Vec<String>,
    /// Case ids it may use; an entry ending in `*` is a prefix (`hospital-a/*`); `*` alone: all.
    pub cases: Vec<String>,
    /// Its roles.
    pub roles: Vec<Role>,
    /// Most streamed sessions it may hold at once (0: the server's `max_sessions_per_principal`).
    #[serde(default)]
    pub max_sessions: usize,
}

/// The auth file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuthFile {
    /// Format version (1).
    pub format: u32,
    /// Health checks answer without credentials (default true: probes carry none).
    #[serde(default = "yes")]
    pub open_health: bool,
    /// Reflection answers without credentials (default true).
    #[serde(default = "yes")]
    pub open_reflection: bool,
    /// The principals.
    pub principals: Vec<PrincipalEntry>,
}

fn yes() -> bool {
    true
}

/// Who is calling, and what it may do.
#[derive(Debug)]
pub struct Principal {
    /// Its name.
    pub name: String,
    cases: Vec<String>,
    roles: BTreeSet<Role>,
    /// Most sessions at once (0: the server's default).
    pub max_sessions: usize,
}

impl Principal {
    /// The principal of a server without `--auth`: every case, every role.
    pub fn anonymous() -> Arc<Self> {
        Arc::new(Self {
            name: "anonymous".into(),
            cases: vec!["*".into()],
            roles: [Role::Read, Role::Register, Role::Manage].into(),
            max_sessions: 0,
        })
    }

    /// Whether it may use (and so see) case `id`.
    pub fn may_use(&self, id: &str) -> bool {
        self.cases.iter().any(|p| match p.strip_suffix('*') {
            Some(prefix) => id.starts_with(prefix),
            None => p == id,
        })
    }

    /// Whether it holds `role` (`register` and `manage` imply `read`).
    pub fn has(&self, role: Role) -> bool {
        self.roles.contains(&role)
            || (role == Role::Read
                && (self.roles.contains(&Role::Register) || self.roles.contains(&Role::Manage)))
    }

    /// PERMISSION_DENIED unless it holds `role`.
    pub fn require(&self, role: Role, what: &str) -> Result<(), ServiceError> {
        if self.has(role) {
            return Ok(());
        }
        Err(PermissionDenied::MissingRole {
            principal: self.name.clone(),
            action: what.to_string(),
            role: role.name(),
        }
        .into())
    }
}

/// Why an auth file is refused; the message names the file and the field.
#[derive(Debug, thiserror::Error)]
#[error("auth file {}: {problem}", path.display())]
pub struct AuthError {
    /// The file.
    pub path: std::path::PathBuf,
    /// What is wrong.
    #[source]
    pub problem: AuthProblem,
}

/// What is wrong with an auth file (or a new token); its text names the field:
/// `principals[I]` is the I-th principal, `[J]` the J-th entry of its list.
#[derive(Debug, thiserror::Error)]
pub enum AuthProblem {
    /// The file does not read.
    #[error("cannot read: {0}")]
    Read(#[source] std::io::Error),
    /// The file is not JSON of the auth file's shape.
    #[error("{0}")]
    Json(#[source] serde_json::Error),
    /// A format other than 1.
    #[error("format {0} is not supported (1)")]
    Format(u32),
    /// A principal's name is empty or longer than 256 characters.
    #[error("principals[{index}].principal: must be 1 to {MAX_NAME} characters")]
    NameLength {
        /// The principal's index.
        index: usize,
    },
    /// A principal is listed twice.
    #[error("principals[{index}].principal: {name:?} is listed twice")]
    DuplicateName {
        /// The second entry's index.
        index: usize,
        /// The name.
        name: String,
    },
    /// A principal with neither token hashes nor certificate subjects.
    #[error(
        "principals[{index}]: neither token_sha256 nor certificate_subjects: it could never \
         authenticate"
    )]
    NoCredentials {
        /// The principal's index.
        index: usize,
    },
    /// A principal with no role.
    #[error("principals[{index}].roles: empty (read, register, manage)")]
    NoRoles {
        /// The principal's index.
        index: usize,
    },
    /// A principal with no case.
    #[error("principals[{index}].cases: empty (case ids, prefixes ending in *, or * for all)")]
    NoCases {
        /// The principal's index.
        index: usize,
    },
    /// A case pattern that is empty or longer than 256 characters.
    #[error("principals[{index}].cases[{case}]: must be 1 to {MAX_NAME} characters")]
    CaseLength {
        /// The principal's index.
        index: usize,
        /// The pattern's index.
        case: usize,
    },
    /// A case pattern with a `*` other than at its end.
    #[error("principals[{index}].cases[{case}]: {pattern:?}: '*' may only end a prefix")]
    CaseWildcard {
        /// The principal's index.
        index: usize,
        /// The pattern's index.
        case: usize,
        /// The pattern.
        pattern: String,
    },
    /// A token hash that is not 64 hex digits.
    #[error(
        "principals[{index}].token_sha256[{token}]: not 64 hex digits (the SHA-256 of the token, \
         never the token itself; `librplus-server token` prints both)"
    )]
    TokenHash {
        /// The principal's index.
        index: usize,
        /// The hash's index.
        token: usize,
    },
    /// A token hash another entry already has.
    #[error("principals[{index}].token_sha256[{token}]: this hash is already another entry's")]
    DuplicateToken {
        /// The principal's index.
        index: usize,
        /// The hash's index.
        token: usize,
    },
    /// An empty certificate subject.
    #[error("principals[{index}].certificate_subjects[{subject}]: empty")]
    EmptySubject {
        /// The principal's index.
        index: usize,
        /// The subject's index.
        subject: usize,
    },
    /// A certificate subject another entry already has.
    #[error(
        "principals[{index}].certificate_subjects[{subject}]: {name:?} is already another entry's"
    )]
    DuplicateSubject {
        /// The principal's index.
        index: usize,
        /// The subject's index.
        subject: usize,
        /// The subject.
        name: String,
    },
    /// The system's random generator failed (making a token).
    #[error("the system's random generator failed")]
    Random,
}

/// The loaded auth file: token hashes and certificate subjects to principals.
#[derive(Debug)]
pub struct Auth {
    tokens: HashMap<[u8; 32], Arc<Principal>>,
    subjects: HashMap<String, Arc<Principal>>,
    /// Health answers without credentials.
    pub open_health: bool,
    /// Reflection answers without credentials.
    pub open_reflection: bool,
}

/// Longest `authorization` header read, bytes.
const MAX_HEADER: usize = 1024;
/// Longest principal name and case pattern, characters.
const MAX_NAME: usize = 256;

/// SHA-256 of `bytes`.
pub fn sha256(bytes: &[u8]) -> [u8; 32] {
    let d = ring::digest::digest(&ring::digest::SHA256, bytes);
    d.as_ref().try_into().expect("SHA-256 is 32 bytes")
}

/// Lower-case hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<[u8; 32]> {
    if s.len() != 64 || !s.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(&s[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(out)
}

/// A new random token (32 bytes from the system's generator, as 64 hex digits) and its SHA-256.
pub fn new_token() -> Result<(String, String), AuthError> {
    use ring::rand::SecureRandom;
    let mut b = [0u8; 32];
    ring::rand::SystemRandom::new()
        .fill(&mut b)
        .map_err(|_| AuthError {
            path: "(token)".into(),
            problem: AuthProblem::Random,
        })?;
    let token = format!("lp_{}", hex(&b));
    let hash = hex(&sha256(token.as_bytes()));
    Ok((token, hash))
}

impl Auth {
    /// Reads and checks an auth file.
    pub fn load(path: &Path) -> Result<Self, AuthError> {
        let err = |problem: AuthProblem| AuthError {
            path: path.to_path_buf(),
            problem,
        };
        let text = std::fs::read_to_string(path).map_err(|e| err(AuthProblem::Read(e)))?;
        let file: AuthFile = serde_json::from_str(&text).map_err(|e| err(AuthProblem::Json(e)))?;
        Self::from_file(file).map_err(err)
    }

    /// Checks a parsed auth file; the error names the field.
    pub fn from_file(file: AuthFile) -> Result<Self, AuthProblem> {
        if file.format != 1 {
            return Err(AuthProblem::Format(file.format));
        }
        let mut tokens = HashMap::new();
        let mut subjects = HashMap::new();
        let mut names = BTreeSet::new();
        for (index, e) in file.principals.into_iter().enumerate() {
            if e.principal.is_empty() || e.principal.chars().count() > MAX_NAME {
                return Err(AuthProblem::NameLength { index });
            }
            if !names.insert(e.principal.clone()) {
                return Err(AuthProblem::DuplicateName {
                    index,
                    name: e.principal,
                });
            }
            if e.token_sha256.is_empty() && e.certificate_subjects.is_empty() {
                return Err(AuthProblem::NoCredentials { index });
            }
            if e.roles.is_empty() {
                return Err(AuthProblem::NoRoles { index });
            }
            if e.cases.is_empty() {
                return Err(AuthProblem::NoCases { index });
            }
            for (case, c) in e.cases.iter().enumerate() {
                if c.is_empty() || c.chars().count() > MAX_NAME {
                    return Err(AuthProblem::CaseLength { index, case });
                }
                if c.strip_suffix('*').unwrap_or(c).contains('*') {
                    return Err(AuthProblem::CaseWildcard {
                        index,
                        case,
                        pattern: c.clone(),
                    });
                }
            }
            let p = Arc::new(Principal {
                name: e.principal.clone(),
                cases: e.cases,
                roles: e.roles.into_iter().collect(),
                max_sessions: e.max_sessions,
            });
            for (token, h) in e.token_sha256.iter().enumerate() {
                let Some(k) = unhex(&h.to_ascii_lowercase()) else {
                    return Err(AuthProblem::TokenHash { index, token });
                };
                if tokens.insert(k, p.clone()).is_some() {
                    return Err(AuthProblem::DuplicateToken { index, token });
                }
            }
            for (subject, s) in e.certificate_subjects.iter().enumerate() {
                if s.is_empty() {
                    return Err(AuthProblem::EmptySubject { index, subject });
                }
                if subjects.insert(s.clone(), p.clone()).is_some() {
                    return Err(AuthProblem::DuplicateSubject {
                        index,
                        subject,
                        name: s.clone(),
                    });
                }
            }
        }
        Ok(Self {
            tokens,
            subjects,
            open_health: file.open_health,
            open_reflection: file.open_reflection,
        })
    }

    /// The caller: its bearer token, else its client certificate's subject. UNAUTHENTICATED
    /// when neither is known (the message never echoes the token).
    pub fn authenticate(
        &self,
        md: &tonic::metadata::MetadataMap,
        peer_certs: Option<&[tonic::transport::CertificateDer<'static>]>,
    ) -> Result<Arc<Principal>, ServiceError> {
        if let Some(v) = md.get("authorization") {
            // Two headers are refused: proxies and servers disagree on which one counts.
            if md.get_all("authorization").iter().nth(1).is_some() {
                return Err(Unauthenticated::RepeatedHeader.into());
            }
            let b = v.as_bytes();
            if b.len() > MAX_HEADER {
                return Err(Unauthenticated::LongHeader {
                    len: b.len(),
                    max: MAX_HEADER,
                }
                .into());
            }
            let s = std::str::from_utf8(b).unwrap_or("");
            let Some(token) = s
                .split_once(' ')
                .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
                .map(|(_, t)| t.trim())
            else {
                return Err(Unauthenticated::NotBearer.into());
            };
            return self
                .tokens
                .get(&sha256(token.as_bytes()))
                .cloned()
                .ok_or_else(|| Unauthenticated::UnknownToken.into());
        }
        if let Some(cert) = peer_certs.and_then(|c| c.first()) {
            for s in subject_names(cert) {
                if let Some(p) = self.subjects.get(&s) {
                    return Ok(p.clone());
                }
            }
            return Err(Unauthenticated::UnknownCertificate.into());
        }
        Err(Unauthenticated::NoCredentials.into())
    }
}

/// The names a certificate's subject is matched by: the whole subject (RFC 4514 form as
/// `x509-parser` prints it) and `CN=` each common name. Empty when the certificate does not parse.
pub fn subject_names(der: &[u8]) -> Vec<String> {
    let Ok((_, cert)) = x509_parser::parse_x509_certificate(der) else {
        return Vec::new();
    };
    let subject = cert.subject();
    let mut out = vec![subject.to_string()];
    out.extend(
        subject
            .iter_common_name()
            .filter_map(|cn| cn.as_str().ok())
            .map(|cn| format!("CN={cn}")),
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(json: &str) -> Result<Auth, AuthProblem> {
        Auth::from_file(serde_json::from_str(json).map_err(AuthProblem::Json)?)
    }

    fn md(auth: &str) -> tonic::metadata::MetadataMap {
        let mut m = tonic::metadata::MetadataMap::new();
        m.insert("authorization", auth.parse().unwrap());
        m
    }

    #[test]
    fn sha256_matches_the_standard_vectors() {
        // FIPS 180-2 test vectors.
        assert_eq!(
            hex(&sha256(b"abc")),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(
            hex(&sha256(b"")),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
        let (t, h) = new_token().unwrap();
        assert_eq!(hex(&sha256(t.as_bytes())), h);
        assert_ne!(new_token().unwrap().0, t);
    }

    #[test]
    fn tokens_map_to_principals_with_their_cases_and_roles() {
        let ha = hex(&sha256(b"token-a"));
        let hb = hex(&sha256(b"token-b"));
        let a = file(&format!(
            r#"{{"format":1,"principals":[
              {{"principal":"a","token_sha256":["{ha}"],"cases":["hosp-a/*","shared"],"roles":["register"]}},
              {{"principal":"b","token_sha256":["{}"],"cases":["*"],"roles":["read"],"max_sessions":1}}]}}"#,
            hb.to_uppercase()
        ))
        .unwrap();
        let p = a.authenticate(&md("Bearer token-a"), None).unwrap();
        assert_eq!(p.name, "a");
        assert!(p.may_use("hosp-a/p1") && p.may_use("shared"));
        assert!(!p.may_use("hosp-b/p1") && !p.may_use("shared2") && !p.may_use("hosp-a"));
        assert!(p.has(Role::Register) && p.has(Role::Read) && !p.has(Role::Manage));
        let b = a.authenticate(&md("bearer  token-b "), None).unwrap();
        assert!(b.may_use("anything") && b.has(Role::Read) && !b.has(Role::Register));
        assert_eq!(b.max_sessions, 1);
        for bad in ["Bearer token-c", "Basic dG9rZW4tYQ==", "token-a", "Bearer "] {
            let e = a.authenticate(&md(bad), None).unwrap_err();
            assert_eq!(e.code(), tonic::Code::Unauthenticated, "{bad}");
            assert!(!e.to_status().message().contains("token-"), "{bad}");
        }
        let e = a
            .authenticate(&tonic::metadata::MetadataMap::new(), None)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated);
        let e = p.require(Role::Manage, "upload cases").unwrap_err();
        assert_eq!(e.code(), tonic::Code::PermissionDenied);
    }

    #[test]
    fn bad_auth_files_name_the_field() {
        let h = hex(&sha256(b"x"));
        for (json, field) in [
            (r#"{"format":2,"principals":[]}"#.to_string(), "format 2"),
            (
                r#"{"format":1,"principals":[{"principal":"a","token_sha256":["secret"],"cases":["*"],"roles":["read"]}]}"#.into(),
                "principals[0].token_sha256[0]",
            ),
            (
                format!(r#"{{"format":1,"principals":[{{"principal":"a","token_sha256":["{h}"],"cases":[],"roles":["read"]}}]}}"#),
                "principals[0].cases",
            ),
            (
                format!(r#"{{"format":1,"principals":[{{"principal":"a","token_sha256":["{h}"],"cases":["a*b"],"roles":["read"]}}]}}"#),
                "principals[0].cases[0]",
            ),
            (
                format!(r#"{{"format":1,"principals":[{{"principal":"a","token_sha256":["{h}"],"cases":["*"],"roles":[]}}]}}"#),
                "principals[0].roles",
            ),
            (
                format!(r#"{{"format":1,"principals":[{{"principal":"a","token_sha256":["{h}"],"cases":["*"],"roles":["read"]}},{{"principal":"b","token_sha256":["{h}"],"cases":["*"],"roles":["read"]}}]}}"#),
                "principals[1].token_sha256[0]",
            ),
            (
                r#"{"format":1,"principals":[{"principal":"a","cases":["*"],"roles":["read"]}]}"#.into(),
                "could never authenticate",
            ),
            (
                format!(r#"{{"format":1,"principals":[{{"principal":"a","token_sha256":["{h}"],"cases":["*"],"roles":["admin"]}}]}}"#),
                "admin",
            ),
        ] {
            let e = file(&json).unwrap_err().to_string();
            assert!(e.contains(field), "{e} should name {field}");
        }
        let e = file(
            r#"{"format":1,"principals":[{"principal":"a","token_sha256":["secret"],"cases":["*"],"roles":["read"]}]}"#,
        )
        .unwrap_err();
        assert!(
            matches!(e, AuthProblem::TokenHash { index: 0, token: 0 }),
            "{e:?}"
        );
        assert_eq!(
            e.to_string(),
            "principals[0].token_sha256[0]: not 64 hex digits (the SHA-256 of the token, never \
             the token itself; `librplus-server token` prints both)"
        );
        let dir = tempfile::tempdir().unwrap();
        let e = Auth::load(&dir.path().join("absent.json")).unwrap_err();
        assert!(matches!(e.problem, AuthProblem::Read(_)), "{e:?}");
        assert!(e.to_string().contains("absent.json: cannot read: "), "{e}");
    }
}
