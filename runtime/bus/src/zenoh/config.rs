//! A host section's zenoh settings: checked without touching files or the network
//! ([`check_settings`]), turned into a zenoh configuration ([`config`]), and the key prefix of
//! a graph's topics ([`key_prefix`]).

use crate::ZenohDecl;

/// The key prefix of the topics a graph sends to `host`: `gprflow/GRAPH/HOST`.
///
/// # Errors
/// A graph or host name that cannot be part of a zenoh key.
pub fn key_prefix(graph: &str, host: &str) -> std::result::Result<String, String> {
    for (what, name) in [("graph name", graph), ("host name", host)] {
        if name.is_empty() || name.contains(['/', '*', '$', '?', '#', ' ']) {
            return Err(format!(
                "{what} `{name}` cannot be part of a zenoh key (no `/ * $ ? #` or spaces)"
            ));
        }
    }
    Ok(format!("gprflow/{graph}/{host}"))
}

/// Checks a host section without touching files or the network: mode, endpoints, lease,
/// link timeout, and that `allow` comes with `tls`.
///
/// # Errors
/// The first problem, in words.
pub fn check_settings(decl: &ZenohDecl) -> std::result::Result<(), String> {
    let mode = decl.mode.as_deref().unwrap_or("peer");
    if !matches!(mode, "peer" | "client" | "router") {
        return Err(format!("zenoh mode `{mode}`: expected peer, client or router"));
    }
    for endpoint in decl.listen.iter().chain(&decl.connect) {
        check_endpoint(endpoint, decl.tls.is_some())?;
    }
    if let Some(lease) = decl.lease_ms
        && lease < 100
    {
        return Err(format!("lease_ms {lease}: at least 100"));
    }
    if let Some(s) = decl.link_timeout_s
        && !(s.is_finite() && s > 0.0)
    {
        return Err(format!("link_timeout_s {s}: must be a positive number of seconds"));
    }
    if !decl.allow.is_empty() && decl.tls.is_none() {
        return Err("`allow` names certificate common names, which needs `tls`".to_owned());
    }
    Ok(())
}

/// The zenoh configuration of a host section: only the endpoints it names, multicast
/// scouting and gossip off unless asked, the admin space off, mutual TLS and access control
/// when configured.
///
/// # Errors
/// A bad setting (see [`check_settings`]) or a missing certificate file, in words.
pub fn config(decl: &ZenohDecl) -> std::result::Result<::zenoh::Config, String> {
    check_settings(decl)?;
    let mut c = ::zenoh::Config::default();
    let mut set = |key: &str, value: serde_json::Value| {
        c.insert_json5(key, &value.to_string())
            .map_err(|e| format!("zenoh setting `{key}` = {value}: {e}"))
    };
    set("mode", decl.mode.as_deref().unwrap_or("peer").into())?;
    set("listen/endpoints", serde_json::json!(decl.listen))?;
    set("connect/endpoints", serde_json::json!(decl.connect))?;
    set("scouting/multicast/enabled", decl.scouting.into())?;
    set("scouting/gossip/enabled", decl.scouting.into())?;
    set("adminspace/enabled", false.into())?;
    if let Some(lease) = decl.lease_ms {
        set("transport/link/tx/lease", lease.into())?;
    }
    if let Some(tls) = &decl.tls {
        for (what, path) in [
            ("root_ca", &tls.root_ca),
            ("certificate", &tls.certificate),
            ("private_key", &tls.private_key),
        ] {
            if !std::path::Path::new(path).is_file() {
                return Err(format!("tls.{what}: {path}: no such file"));
            }
        }
        set("transport/link/tls/root_ca_certificate", tls.root_ca.as_str().into())?;
        set("transport/link/tls/listen_certificate", tls.certificate.as_str().into())?;
        set("transport/link/tls/listen_private_key", tls.private_key.as_str().into())?;
        set(
            "transport/link/tls/connect_certificate",
            tls.certificate.as_str().into(),
        )?;
        set(
            "transport/link/tls/connect_private_key",
            tls.private_key.as_str().into(),
        )?;
        set("transport/link/tls/enable_mtls", true.into())?;
        set("transport/link/tls/verify_name_on_connect", true.into())?;
    }
    if !decl.allow.is_empty() {
        set(
            "access_control",
            serde_json::json!({
                "enabled": true,
                "default_permission": "deny",
                "rules": [{
                    "id": "gprflow_topics",
                    "key_exprs": ["gprflow/**"],
                    "messages": ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                                 "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                    "flows": ["egress", "ingress"],
                    "permission": "allow",
                }],
                "subjects": [{ "id": "allowed_hosts", "cert_common_names": decl.allow }],
                "policies": [{ "rules": ["gprflow_topics"], "subjects": ["allowed_hosts"] }],
            }),
        )?;
    }
    Ok(c)
}

fn check_endpoint(endpoint: &str, tls: bool) -> std::result::Result<(), String> {
    let Some((proto, address)) = endpoint.split_once('/') else {
        return Err(format!(
            "endpoint `{endpoint}`: expected PROTOCOL/ADDRESS:PORT (tcp/10.0.0.1:7447)"
        ));
    };
    match proto {
        "tcp" => {}
        "tls" if tls => {}
        "tls" => {
            return Err(format!(
                "endpoint `{endpoint}`: a tls/ endpoint needs the host's `tls:` certificates"
            ));
        }
        _ => {
            return Err(format!(
                "endpoint `{endpoint}`: protocol `{proto}` is not built in (tcp, tls)"
            ));
        }
    }
    let address = address.split('#').next().unwrap_or(address);
    if address
        .rsplit_once(':')
        .is_none_or(|(_, port)| port.parse::<u16>().is_err())
    {
        return Err(format!("endpoint `{endpoint}`: expected ADDRESS:PORT after `{proto}/`"));
    }
    Ok(())
}
