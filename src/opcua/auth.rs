//! Who may connect: the `[opcua]` users (Argon2 password hashes, never the passwords; or an
//! X.509 user certificate, known by its SHA-1 thumbprint) and, only when configured,
//! anonymous clients. Every user reads; nobody writes or calls a method.

use argon2::password_hash::{PasswordHash, PasswordHasher, PasswordVerifier, SaltString};
use argon2::Argon2;
use async_trait::async_trait;
use opcua::crypto::{SecurityPolicy, Thumbprint};
use opcua::server::address_space::AccessLevel;
use opcua::server::authenticator::{user_pass_security_policy_id, AuthManager, Password, UserToken};
use opcua::server::ServerEndpoint;
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};

/// The Argon2id PHC string of `password` with a fresh random salt (`cncgw opcua-hash`).
pub fn hash_password(password: &str) -> Result<String, String> {
    let mut salt = [0u8; 16];
    std::io::Read::read_exact(&mut std::fs::File::open("/dev/urandom").map_err(|e| format!("/dev/urandom: {e}"))?, &mut salt)
        .map_err(|e| format!("/dev/urandom: {e}"))?;
    let salt = SaltString::encode_b64(&salt).map_err(|e| e.to_string())?;
    Argon2::default().hash_password(password.as_bytes(), &salt).map(|h| h.to_string()).map_err(|e| e.to_string())
}

/// True if `password` matches the PHC string `hash` (false for a hash that does not parse).
pub fn verify_password(hash: &str, password: &str) -> bool {
    PasswordHash::new(hash).is_ok_and(|h| Argon2::default().verify_password(password.as_bytes(), &h).is_ok())
}

/// A hash to verify against when the user name is unknown, so that an unknown user takes as
/// long to refuse as a wrong password (no user enumeration by timing).
const DUMMY_HASH: &str = "$argon2id$v=19$m=19456,t=2,p=1$AAAAAAAAAAAAAAAAAAAAAA$7Lr2vjl1bIZ5pNsXvqVv9u5LtbL8QCOT6c7NaECzJ5s";

/// The `[opcua]` users as async-opcua's authenticator.
pub struct Users {
    pub anonymous: bool,
    /// (name, PHC hash).
    pub users: Vec<(String, String)>,
    /// (name, SHA-1 thumbprint of the user's certificate).
    pub certificates: Vec<(String, [u8; 20])>,
}

/// async-opcua's policy id of X.509 user tokens: it refuses a token that names another
/// (its constant is crate-private).
const POLICY_ID_X509: &str = "x509";

#[async_trait]
impl AuthManager for Users {
    async fn authenticate_anonymous_token(&self, _endpoint: &ServerEndpoint) -> Result<(), Error> {
        if self.anonymous {
            Ok(())
        } else {
            Err(Error::new(StatusCode::BadIdentityTokenRejected, "anonymous access is off ([opcua] anonymous = false)"))
        }
    }

    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        let hash = self.users.iter().find(|(n, _)| n == username).map(|(_, h)| h.clone());
        let known = hash.is_some();
        let hash = hash.unwrap_or_else(|| DUMMY_HASH.to_string());
        let pw = password.get().to_string();
        // Argon2 takes tens of ms by design: off the server's task.
        let ok = tokio::task::spawn_blocking(move || verify_password(&hash, &pw)).await.unwrap_or(false);
        if ok && known {
            tracing::info!(user = username, "opcua: user signed in");
            Ok(UserToken(username.to_string()))
        } else {
            tracing::warn!(user = username, "opcua: wrong user name or password");
            Err(Error::new(StatusCode::BadUserAccessDenied, "wrong user name or password"))
        }
    }

    /// Called once async-opcua has checked the token's signature (the client holds the
    /// certificate's private key, OPC 10000-4 7.36.5); here only: is it a configured user's.
    async fn authenticate_x509_identity_token(&self, _endpoint: &ServerEndpoint, signing_thumbprint: &Thumbprint) -> Result<UserToken, Error> {
        match self.certificates.iter().find(|(_, t)| t[..] == *signing_thumbprint.value()) {
            Some((name, _)) => {
                tracing::info!(user = name.as_str(), "opcua: certificate user signed in");
                Ok(UserToken(name.clone()))
            }
            None => {
                tracing::warn!(thumbprint = signing_thumbprint.as_hex_string(), "opcua: unknown user certificate");
                Err(Error::new(StatusCode::BadIdentityTokenRejected, "unknown user certificate"))
            }
        }
    }

    /// Read-only: whatever a node says, a user may only read it.
    fn effective_user_access_level(&self, _token: &UserToken, user_access_level: AccessLevel, _node_id: &NodeId) -> AccessLevel {
        user_access_level & (AccessLevel::CURRENT_READ | AccessLevel::HISTORY_READ)
    }

    /// No method changes the machine; none is callable.
    fn is_user_executable(&self, _token: &UserToken, _method_id: &NodeId) -> bool {
        false
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        let mut p = Vec::new();
        if self.anonymous {
            p.push(UserTokenPolicy {
                policy_id: UAString::from("anonymous"),
                token_type: UserTokenType::Anonymous,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        if !self.users.is_empty() {
            p.push(UserTokenPolicy {
                policy_id: user_pass_security_policy_id(endpoint),
                token_type: UserTokenType::UserName,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        if !self.certificates.is_empty() {
            // The policy the client signs its token with (async-opcua verifies with this one):
            // the endpoint's, and on a None endpoint Basic256Sha256 (the token is signed even
            // when the channel is not).
            let sp = match endpoint.security_policy() {
                SecurityPolicy::None | SecurityPolicy::Unknown => SecurityPolicy::Basic256Sha256,
                sp => sp,
            };
            p.push(UserTokenPolicy {
                policy_id: UAString::from(POLICY_ID_X509),
                token_type: UserTokenType::Certificate,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::from(sp.to_uri()),
            });
        }
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_hash_verifies_its_password_only() {
        let h = hash_password("spindle").unwrap();
        assert!(h.starts_with("$argon2id$v=19$"), "{h}");
        assert!(verify_password(&h, "spindle"));
        assert!(!verify_password(&h, "Spindle"));
        assert!(!verify_password("not a hash", "spindle"));
        assert_ne!(h, hash_password("spindle").unwrap(), "a fresh salt each time");
        assert!(PasswordHash::new(DUMMY_HASH).is_ok());
    }
}
