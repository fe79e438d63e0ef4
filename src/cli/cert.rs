//! `tessera cert`: what a farm needs to run over TLS with tokens, made
//! here with no other tool: a CA certificate, a coordinator certificate it
//! signs, and (with `--tokens`) a client and a worker token.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Args;
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};

#[derive(Args, Debug)]
pub struct CertArgs {
    /// Folder to write ca.pem, coordinator.pem and coordinator.key into
    #[arg(long, short, default_value = "tessera-tls")]
    pub out: PathBuf,
    /// A host name or IP address clients use to reach the coordinator
    /// (repeat for several) [default: localhost, 127.0.0.1, ::1 and this
    /// machine's host name]
    #[arg(long = "name", value_name = "HOST")]
    pub names: Vec<String>,
    /// Also write client.token and worker.token (random, 256 bits)
    #[arg(long)]
    pub tokens: bool,
    /// Replace files that exist
    #[arg(long)]
    pub force: bool,
}

fn write_private(path: &Path, data: &[u8], private: bool) -> Result<()> {
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create(true).truncate(true);
    #[cfg(unix)]
    if private {
        use std::os::unix::fs::OpenOptionsExt as _;
        o.mode(0o600);
    }
    o.open(path)
        .and_then(|mut f| f.write_all(data))
        .with_context(|| format!("cannot write {}", path.display()))
}

pub fn run(args: CertArgs) -> Result<ExitCode> {
    let mut names = args.names.clone();
    if names.is_empty() {
        names = vec!["localhost".into(), "127.0.0.1".into(), "::1".into()];
        if let Ok(h) = std::fs::read_to_string("/etc/hostname") {
            let h = h.trim();
            if !h.is_empty() && h != "localhost" {
                names.push(h.to_string());
            }
        }
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut files = vec!["ca.pem", "coordinator.pem", "coordinator.key"];
    if args.tokens {
        files.extend(["client.token", "worker.token"]);
    }
    if !args.force
        && let Some(f) = files.iter().find(|f| args.out.join(f).exists())
    {
        bail!(
            "{} exists; pass --force to replace it",
            args.out.join(f).display()
        );
    }

    let mut ca = CertificateParams::new(Vec::<String>::new())?;
    ca.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca.distinguished_name
        .push(DnType::CommonName, "Tessera farm CA");
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let ca_key = KeyPair::generate()?;
    let ca_cert = ca.self_signed(&ca_key)?;
    let issuer = Issuer::new(ca, ca_key);

    let mut leaf = CertificateParams::new(names.clone())
        .with_context(|| format!("invalid --name among {names:?}"))?;
    leaf.distinguished_name
        .push(DnType::CommonName, "Tessera coordinator");
    leaf.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    leaf.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
    let leaf_key = KeyPair::generate()?;
    let leaf_cert = leaf.signed_by(&leaf_key, &issuer)?;

    let out = &args.out;
    write_private(&out.join("ca.pem"), ca_cert.pem().as_bytes(), false)?;
    write_private(
        &out.join("coordinator.pem"),
        leaf_cert.pem().as_bytes(),
        false,
    )?;
    write_private(
        &out.join("coordinator.key"),
        leaf_key.serialize_pem().as_bytes(),
        true,
    )?;
    if args.tokens {
        for f in ["client.token", "worker.token"] {
            let t = super::farm_common::new_token()? + "\n";
            write_private(&out.join(f), t.as_bytes(), true)?;
        }
    }
    eprintln!(
        "wrote {} in {} (coordinator certificate for {})",
        files.join(", "),
        out.display(),
        names.join(", ")
    );
    eprintln!(
        "coordinator: tessera coordinator --tls-cert {0}/coordinator.pem --tls-key {0}/coordinator.key{1}",
        out.display(),
        if args.tokens {
            format!(
                " --client-token-file {0}/client.token --worker-token-file {0}/worker.token",
                out.display()
            )
        } else {
            String::new()
        }
    );
    eprintln!(
        "others:      --coordinator https://{}:7878 --ca {}/ca.pem{}",
        names[0],
        out.display(),
        if args.tokens {
            " --token-file client.token|worker.token"
        } else {
            ""
        }
    );
    Ok(ExitCode::SUCCESS)
}
