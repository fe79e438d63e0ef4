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
    /// Sign with this existing CA key (the ca.key an earlier `tessera
    /// cert` wrote; its ca.pem beside it) instead of making a new CA: a
    /// coordinator certificate for more host names that every host's
    /// ca.pem already trusts
    #[arg(long, value_name = "FILE")]
    pub ca_key: Option<PathBuf>,
}

/// The CA's distinguished name: a CA made again from its key (`--ca-key`)
/// must name itself as the first one did, or its certificates would name
/// an issuer that no ca.pem is.
const CA_NAME: &str = "Tessera farm CA";

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
    // The CA: a new one, or the existing one of --ca-key (its certificate
    // read from beside it, and written out unchanged where that is
    // another folder).
    let existing = match &args.ca_key {
        Some(key) => {
            let pem = std::fs::read_to_string(key)
                .with_context(|| format!("cannot read --ca-key {}", key.display()))?;
            let ca_key = KeyPair::from_pem(&pem).with_context(|| {
                format!(
                    "--ca-key {} is not a PEM private key (the ca.key of `tessera cert`)",
                    key.display()
                )
            })?;
            let ca_pem_path = key.with_file_name("ca.pem");
            let ca_pem = std::fs::read(&ca_pem_path).with_context(|| {
                format!(
                    "cannot read {}, the CA certificate that goes with --ca-key {}",
                    ca_pem_path.display(),
                    key.display()
                )
            })?;
            let same_folder = std::fs::canonicalize(key.parent().unwrap_or(Path::new(".")))
                .ok()
                .zip(std::fs::canonicalize(&args.out).ok())
                .is_some_and(|(a, b)| a == b);
            Some((ca_key, ca_pem, same_folder))
        }
        None => None,
    };
    let mut files = match &existing {
        Some((_, _, true)) => vec!["coordinator.pem", "coordinator.key"],
        _ => vec!["ca.pem", "ca.key", "coordinator.pem", "coordinator.key"],
    };
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
    ca.distinguished_name.push(DnType::CommonName, CA_NAME);
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let (ca_key, ca_pem, ca_new) = match existing {
        Some((key, pem, same_folder)) => (key, pem, !same_folder),
        None => {
            let key = KeyPair::generate()?;
            let pem = ca.self_signed(&key)?.pem().into_bytes();
            (key, pem, true)
        }
    };
    let ca_key_pem = ca_key.serialize_pem();
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
    if ca_new {
        write_private(&out.join("ca.pem"), &ca_pem, false)?;
        // Kept (owner-only) so that `--ca-key` can later sign a
        // certificate for more names with the CA every host trusts.
        write_private(&out.join("ca.key"), ca_key_pem.as_bytes(), true)?;
    }
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
