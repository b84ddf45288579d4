"""`labcal certificate`: make a key pair, approve (sign) a run's certificate, verify a signature."""

from __future__ import annotations

import argparse

from labcal.commands.common import add_db_option, out, print_json


def cmd_keygen(args: argparse.Namespace) -> int:
    from labcal.documents.approval import key_id, keygen, load_public_key

    private, public = keygen(args.out)
    kid = key_id(load_public_key(public))
    if args.json:
        print_json({"private_key": str(private), "public_key": str(public), "key_id": kid})
        return 0
    out.print(f"private key {private} (readable by you only: keep it so), public key {public}")
    out.print(f"key id {kid}; give the public key to whoever verifies your certificates")
    return 0


def cmd_approve(args: argparse.Namespace) -> int:
    from pathlib import Path

    from labcal.documents.approval import approve, load_private_key
    from labcal.documents.certificate import read_certificate
    from labcal.documents.report import CERTIFICATE, fitted, write_documents
    from labcal.run.record import load_run

    key = load_private_key(args.key)  # before anything is read or written
    record = load_run(args.run_dir)
    cert = approve(read_certificate(Path(args.run_dir) / CERTIFICATE), args.by, args.role, key)
    fit, device, _ = fitted(record)
    result = write_documents(cert, record, fit, device, args.db)
    if args.json:
        print_json({"certificate": str(result.certificate_path), "number": cert.number,
                    "approved_by": args.by, "role": args.role, "key_id": cert.approval.key_id
                    if cert.approval else None, "report_pdf": str(result.pdf_path)})
        return 0
    out.print(f"Certificate {cert.number} approved by {args.by} ({args.role}) and signed: "
              f"{result.certificate_path}; report {result.pdf_path} no longer says DRAFT")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from labcal.documents.approval import load_public_key, verify

    cert = verify(args.file, load_public_key(args.public_key))
    approval = cert.approval
    assert approval is not None  # verify refuses an unapproved certificate
    if args.json:
        print_json({"file": args.file, "valid": True, "number": cert.number, "approved_by": approval.by,
                    "role": approval.role, "approved_utc": approval.approved_utc.isoformat()})
        return 0
    out.print(f"{args.file}: signature valid — certificate {cert.number}, approved by {approval.by} "
              f"({approval.role}) on {approval.approved_utc:%Y-%m-%d %H:%M} UTC")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("certificate", help="approve (sign) a certificate, verify a signature, make keys",
                       description="An issued certificate is a DRAFT until approved: `approve` signs it with "
                                   "the approver's Ed25519 private key; `verify` checks a certificate.json "
                                   "against the laboratory's public key and fails on any change.")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    keygen = verbs.add_parser("keygen", help="make an Ed25519 key pair (private key readable by you only)")
    keygen.add_argument("--out", required=True, metavar="PREFIX", help="writes PREFIX.key and PREFIX.pub")
    keygen.add_argument("--json", action="store_true", help="print as JSON on stdout")
    keygen.set_defaults(func=cmd_keygen)
    approve = verbs.add_parser("approve", help="approve and sign a run's certificate",
                               description="Sign RUN_DIR/certificate.json, regenerate the report without "
                                           "DRAFT, and store the approved certificate in the history.")
    approve.add_argument("run_dir", metavar="RUN_DIR", help="the run directory holding certificate.json")
    approve.add_argument("--by", required=True, metavar="NAME", help="the approver's name")
    approve.add_argument("--role", required=True, metavar="ROLE", help="the approver's role, e.g. 'Technical "
                                                                       "manager'")
    approve.add_argument("--key", required=True, metavar="KEYFILE", help="the approver's private key (PEM)")
    add_db_option(approve)
    approve.add_argument("--json", action="store_true", help="print as JSON on stdout")
    approve.set_defaults(func=cmd_approve)
    verify = verbs.add_parser("verify", help="verify a certificate's signature (exit 2 if it fails)")
    verify.add_argument("file", metavar="FILE", help="a certificate.json")
    verify.add_argument("--public-key", required=True, metavar="KEY",
                        help="the laboratory's public key (PEM)")
    verify.add_argument("--json", action="store_true", help="print as JSON on stdout")
    verify.set_defaults(func=cmd_verify)
