//! The read-only OPC UA server of `cncgw run` (`[opcua]`, feature `opcua`), on async-opcua.
//!
//! Floor: between `cli` and `control` — it reads `control::snapshot` (and `config`,
//! `alarm`); only `cli::run` starts it. It runs on its own thread with its own tokio runtime,
//! started before the cycle thread takes its real-time policy, and never touches the cycle:
//! a task copies the lock-free snapshot every [`UPDATE_MS`] into the address space
//! (`space`), and sends the alarm the run stopped on as an event of an alarm condition
//! (`condition`, with ConditionRefresh).
//!
//! Secure by default (`config::OpcUaConfig`): Sign&Encrypt endpoints only unless `none` is
//! allowed on loopback; the server's certificate is made on first start under
//! `STATE_DIR/opcua/pki/own/` (kept, so that clients trust it once); a client's certificate
//! is refused into `pki/rejected/` until an administrator moves it to `pki/trusted/`; users
//! sign in with passwords checked against Argon2 hashes or with a configured X.509 user
//! certificate (`auth`); anonymous only if configured. Nothing is writable and no method is callable.

mod auth;
mod condition;
mod space;

pub use auth::{hash_password, verify_password};

use crate::config::MachineConfig;
use crate::control::snapshot::Snapshot;
use opcua::crypto::SecurityPolicy;
use opcua::server::diagnostics::{DiagnosticsNodeManagerBuilder, NamespaceMetadata};
use opcua::server::node_manager::memory::{simple_node_manager, CoreNodeManagerBuilder, InMemoryNodeManagerBuilder, SimpleNodeManager};
use opcua::server::{ServerBuilder, ServerHandle, ServerUserToken, ANONYMOUS_USER_TOKEN_ID};
use opcua::types::MessageSecurityMode;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

/// The namespace of what OPC 40501-1 has no place for (and of the 40501 names, whose
/// companion nodesets are not loaded: see `space`).
pub const NAMESPACE: &str = "urn:cncgw:machine-tool";

/// How often the server copies the snapshot into its variables, ms.
pub const UPDATE_MS: u64 = 50;

/// A running server; [`OpcUaServer::finish`] it after the run.
pub struct OpcUaServer {
    handle: ServerHandle,
    thread: Option<std::thread::JoinHandle<()>>,
    linger: Duration,
    /// The address it listens on.
    pub addr: SocketAddr,
}

/// What the server's thread reports once it listens (or why it cannot).
type Ready = Result<(ServerHandle, SocketAddr), String>;

impl OpcUaServer {
    /// Start the server `cfg.opcua` describes, reading `snapshot`; its PKI (own certificate,
    /// trusted and rejected clients) under `state_dir/opcua/pki`. Returns once it listens:
    /// an error (port taken, certificate not writable) is the caller's to refuse the run with.
    pub fn start(cfg: &MachineConfig, config_name: &str, snapshot: Arc<Snapshot>, state_dir: &Path) -> Result<OpcUaServer, String> {
        let oc = &cfg.opcua;
        let pki = state_dir.join("opcua").join("pki");
        let certificates = user_certificates(oc, Path::new(config_name).parent())?;
        std::fs::create_dir_all(&pki).map_err(|e| format!("opcua: cannot create {}: {e}", pki.display()))?;
        let bind = format!("{}:{}", oc.host, oc.port);
        let config_name = config_name.to_string();
        let cfg = cfg.clone();
        let (tx, rx) = std::sync::mpsc::channel::<Ready>();
        let conditions = condition::Shared::default();
        let thread = std::thread::Builder::new()
            .name("opcua".into())
            .spawn(move || {
                // The builder is not Send: made here, on the server's thread.
                let b = builder(&cfg, &pki, conditions.clone(), certificates);
                let rt =
                    tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| format!("opcua: cannot start its runtime: {e}"));
                match (b, rt) {
                    (Ok(b), Ok(rt)) => rt.block_on(serve(b, bind, cfg.machine.name.clone(), config_name, snapshot, conditions, tx)),
                    (Err(e), _) | (_, Err(e)) => {
                        let _ = tx.send(Err(e));
                    }
                }
            })
            .map_err(|e| format!("opcua: cannot start its thread: {e}"))?;
        let linger = Duration::from_millis(oc.linger_ms as u64);
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(Ok((handle, addr))) => Ok(OpcUaServer { handle, thread: Some(thread), linger, addr }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => Err("opcua: the server did not start within 60 s".into()),
        }
    }

    /// After the run: stay up `linger_ms` so that subscribed clients receive the final state
    /// and the alarm, then close every session and stop.
    pub fn finish(mut self) {
        std::thread::sleep(self.linger);
        self.stop();
    }

    fn stop(&mut self) {
        self.handle.cancel();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for OpcUaServer {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The server's configuration: endpoints (one per policy, Sign&Encrypt, or None), users,
/// certificates.
fn builder(cfg: &MachineConfig, pki: &Path, conditions: condition::Shared, certificates: Vec<(String, [u8; 20])>) -> Result<ServerBuilder, String> {
    let oc = &cfg.opcua;
    let password_users: Vec<(&str, &str)> = oc.users.iter().filter_map(|u| Some((u.name.as_str(), u.password_hash.as_deref()?))).collect();
    let mut ids: Vec<String> = password_users.iter().map(|(n, _)| format!("user:{n}")).collect();
    if oc.anonymous {
        ids.push(ANONYMOUS_USER_TOKEN_ID.to_string());
    }
    let ids: Vec<&str> = ids.iter().map(String::as_str).collect();
    let uri = machine_uri(&cfg.machine.name);
    // The default node managers (core, diagnostics) with, first, the one that answers
    // ConditionRefresh (a core method the core manager does not implement).
    let mut b = ServerBuilder::new()
        .without_node_managers()
        .with_node_manager(condition::RefreshMethods::builder(conditions))
        .with_node_manager(InMemoryNodeManagerBuilder::new(CoreNodeManagerBuilder))
        .with_node_manager(DiagnosticsNodeManagerBuilder)
        // The certificate's subject is made from it: no RDN syntax (`+`, `,`, `/`, `=`) in it.
        .application_name(format!(
            "cncgw {}",
            cfg.machine.name.chars().map(|c| if c.is_ascii_alphanumeric() || " -_.".contains(c) { c } else { '_' }).collect::<String>()
        ))
        .application_uri(uri)
        .product_uri("urn:cncgw")
        .host(oc.host.clone())
        .port(oc.port)
        .pki_dir(pki)
        // Made on first start (2048-bit RSA, self-signed), kept for the next.
        .create_sample_keypair(true)
        .trust_client_certs(false)
        .discovery_urls(vec!["/".to_string()])
        .diagnostics_enabled(false)
        .with_authenticator(Arc::new(auth::Users {
            anonymous: oc.anonymous,
            users: password_users.iter().map(|(n, h)| (n.to_string(), h.to_string())).collect(),
            certificates,
        }));
    for (name, hash) in &password_users {
        // async-opcua wants a token per user; `auth::Users` checks the password, against the
        // hash (the token's own password is never compared). Certificate users need none:
        // `auth::Users` offers their token policy itself.
        b = b.add_user_token(format!("user:{name}"), ServerUserToken::user_pass(*name, *hash));
    }
    for p in &oc.security_policies {
        let (policy, mode) = match p.as_str() {
            "none" => (SecurityPolicy::None, MessageSecurityMode::None),
            "basic256sha256" => (SecurityPolicy::Basic256Sha256, MessageSecurityMode::SignAndEncrypt),
            "aes128sha256rsaoaep" => (SecurityPolicy::Aes128Sha256RsaOaep, MessageSecurityMode::SignAndEncrypt),
            "aes256sha256rsapss" => (SecurityPolicy::Aes256Sha256RsaPss, MessageSecurityMode::SignAndEncrypt),
            other => return Err(format!("opcua: unknown security policy {other:?}")),
        };
        b = b.add_endpoint(p.as_str(), ("/", policy, mode, &ids as &[&str]));
    }
    Ok(b.with_node_manager(simple_node_manager(NamespaceMetadata { namespace_uri: NAMESPACE.into(), ..Default::default() }, "cncgw")))
}

/// The certificate users' (name, SHA-1 thumbprint): given, or of their certificate file
/// (relative: to `config_dir`), which must be readable and valid now.
fn user_certificates(oc: &crate::config::OpcUaConfig, config_dir: Option<&Path>) -> Result<Vec<(String, [u8; 20])>, String> {
    let mut out = Vec::new();
    for (i, u) in oc.users.iter().enumerate() {
        if let Some(t) = u.thumbprint_bytes() {
            out.push((u.name.clone(), t));
        } else if let Some(file) = &u.certificate {
            let path = config_dir.map_or_else(|| Path::new(file).to_path_buf(), |d| d.join(file));
            let bytes = std::fs::read(&path).map_err(|e| format!("opcua.users[{i}].certificate: cannot read {}: {e}", path.display()))?;
            let cert = opcua::crypto::X509::from_der(&bytes)
                .or_else(|_| opcua::crypto::X509::from_pem(&bytes))
                .map_err(|e| format!("opcua.users[{i}].certificate: {} is no X.509 certificate (DER or PEM): {e}", path.display()))?;
            cert.is_time_valid(&opcua::types::DateTime::now().as_chrono())
                .map_err(|e| format!("opcua.users[{i}].certificate: {} is not valid now: {e}", path.display()))?;
            let mut t = [0u8; 20];
            t.copy_from_slice(cert.thumbprint().value());
            out.push((u.name.clone(), t));
        }
    }
    Ok(out)
}

/// `urn:cncgw:NAME`, the machine's name with what a URN does not take as `_`.
pub(crate) fn machine_uri(name: &str) -> String {
    let n: String = name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '.' { c } else { '_' }).collect();
    format!("urn:cncgw:{n}")
}

/// The server's thread: build, bind, say ready, run until cancelled, with the task that
/// copies the snapshot in.
async fn serve(
    builder: ServerBuilder,
    bind: String,
    machine: String,
    config_name: String,
    snapshot: Arc<Snapshot>,
    conditions: condition::Shared,
    tx: std::sync::mpsc::Sender<Ready>,
) {
    let (server, handle) = match builder.build() {
        Ok(s) => s,
        Err(e) => {
            let _ = tx.send(Err(format!("opcua: {e}")));
            return;
        }
    };
    // async-opcua only warns when it has no certificate; encrypted endpoints would then fail
    // every client: refuse instead.
    if handle.info().config.endpoints.values().any(|e| e.security_policy.parse::<SecurityPolicy>() != Ok(SecurityPolicy::None)) {
        let pki = &handle.info().config.pki_dir;
        for f in ["own/cert.der", "private/private.pem"] {
            if !pki.join(f).is_file() {
                let _ = tx.send(Err(format!("opcua: no server certificate: {} could not be made (see the log)", pki.join(f).display())));
                return;
            }
        }
    }
    let listener = match tokio::net::TcpListener::bind(&bind).await {
        Ok(l) => l,
        Err(e) => {
            let _ = tx.send(Err(format!("opcua: cannot listen on {bind}: {e}")));
            return;
        }
    };
    let addr = listener.local_addr().ok();
    let Some(nm) = handle.node_managers().get_of_type::<SimpleNodeManager>() else {
        let _ = tx.send(Err("opcua: the node manager is missing".into()));
        return;
    };
    let ns = handle.get_namespace_index(NAMESPACE).unwrap_or(1);
    let mut space = space::Space::build(&nm, &handle, ns, &machine, &config_name, &snapshot.info().axes);
    let _ = conditions.set(space.conditions());
    let h = handle.clone();
    let updater = async move {
        let mut tick = tokio::time::interval(Duration::from_millis(UPDATE_MS));
        loop {
            tokio::select! {
                _ = h.token().cancelled() => break,
                _ = tick.tick() => space.update(&nm, &h, &snapshot),
            }
        }
    };
    let _ = tx.send(addr.map(|a| (handle.clone(), a)).ok_or_else(|| "opcua: no local address".to_string()));
    let (r, ()) = tokio::join!(server.run_with(listener), updater);
    if let Err(e) = r {
        tracing::warn!("opcua: the server stopped: {e}");
    }
}
