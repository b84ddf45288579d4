"""`labcal certificate`: make a key pair, register approvers, approve (sign) a run's certificate,
verify a signature."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, err, out, print_json
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import certificates
else:
    certificates = lazy("labcal.app.certificates")  # not for --help: SQLAlchemy, scipy, matplotlib


def _share(db: str | None) -> None:
    """Send what the command recorded to the lab's server now; one line on stderr when it cannot."""
    unsent = certificates.share_with_lab(db)
    if unsent:
        err.print(unsent, markup=False)


def cmd_keygen(args: argparse.Namespace) -> int:
    keys = certificates.make_keys(certificates.MakeKeys(args.out))
    if args.json:
        print_json({"private_key": str(keys.private_key), "public_key": str(keys.public_key),
                    "key_id": keys.key_id})
        return 0
    out.print(f"private key {keys.private_key} (readable by you only: keep it so), public key "
              f"{keys.public_key}")
    out.print(f"key id {keys.key_id}; give the public key to whoever verifies your certificates")
    return 0


def cmd_approve(args: argparse.Namespace) -> int:
    request = certificates.ApproveCertificate(args.run_dir, args.by, args.role, args.key, args.db,
                                              args.station, unchained=args.unchained)
    approved = certificates.approve_certificate(request)
    _share(args.db)
    if args.json:
        print_json(approved.to_json())
        return 0
    result = approved.outputs
    cert = result.certificate
    approval = cert.approval
    assert approval is not None  # approve_run signs or refuses
    out.print(f"Certificate {cert.number} approved by {approval.by} ({approval.role}) and signed, with its "
              f"DCC: {result.certificate_path}; report {result.pdf_path} no longer says DRAFT")
    return 0


def cmd_approvers_add(args: argparse.Namespace) -> int:
    a = certificates.add_approver(certificates.AddApprover(args.name, args.role, args.public_key, args.db))
    _share(args.db)
    if args.json:
        print_json(a.to_json())
        return 0
    if a.role == certificates.SERVER_ROLE:
        out.print(f"{a.name}: the lab server's key {a.key_id[:12]}… (`labcal serve --key`) signs for every "
                  "approver signed in to the server, and as nobody itself")
    else:
        out.print(f"{a.name} ({a.role}) may approve certificates with key {a.key_id[:12]}…")
    return 0


def cmd_approvers_list(args: argparse.Namespace) -> int:
    listed = certificates.list_approvers(certificates.ListApprovers(args.db))
    found = listed.approvers
    if listed.stale:
        err.print(listed.stale, markup=False)
    if args.json:
        print_json({"database": listed.database, "approvers": [a.to_json() for a in found]})
        return 0
    if not found:
        missing = "" if listed.exists else " (it does not exist yet)"
        # a path is not markup
        out.print(f"no approvers registered in {listed.database}{missing} (`labcal certificate approvers add "
                  "NAME --role ROLE --public-key FILE`)", markup=False, soft_wrap=True)
    for a in found:
        state = "active" if a.active else f"revoked {a.revoked_utc}"
        out.print(f"{a.name}\t{a.role}\tkey {a.key_id[:12]}…\tadded {a.added_utc}\t{state}")
    return 0


def cmd_approvers_revoke(args: argparse.Namespace) -> int:
    a = certificates.revoke_approver(certificates.RevokeApprover(args.name, args.db))
    _share(args.db)
    if args.json:
        print_json(a.to_json())
        return 0
    out.print(f"{a.name}'s key {a.key_id[:12]}… revoked at {a.revoked_utc}: it approves nothing from now on, "
              "and certificates it signed no longer verify")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    v = certificates.verify_certificate(
        certificates.VerifyCertificate(args.file, args.public_key, args.dcc, args.db))
    if args.json:
        print_json(v.to_json())
        return 0
    who = (f"approved by {v.approved_by} ({v.role})" if v.through_server is None else
           f"approved by {v.approved_by} (an approver of the lab server, user {v.through_server['user_id']}, "
           f"{v.through_server['authentication']}) through the lab server's key "
           f"({v.through_server['signer']})")
    out.print(f"{v.file}: signature valid against {v.verified_against} — certificate {v.number}, {who} on "
              f"{v.approved_utc:%Y-%m-%d %H:%M} UTC"
              + (f"; DCC {v.dcc} is the one signed" if v.dcc is not None else "; no DCC signed with it")
              + f"; {v.journal}")
    return 0


APPROVE_HELP = ("Sign RUN_DIR/certificate.json and its DCC, regenerate the report without DRAFT, and store "
                "the approved certificate in the history. Refused (naming every reason) for a simulated "
                "run, a draft that the certificate rebuilt from the journal does not reproduce, and a key "
                "that is not registered to --by and --role or is revoked.")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("certificate", help=summary("certificate"),
                       description="An issued certificate is a DRAFT until approved: `approve` signs it with "
                                   "the approver's Ed25519 private key; `verify` checks a certificate.json "
                                   "against the laboratory's public key and fails on any change.")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    keygen = verbs.add_parser("keygen", help="make an Ed25519 key pair (private key readable by you only)")
    keygen.add_argument("--out", required=True, metavar="PREFIX", help="writes PREFIX.key and PREFIX.pub")
    keygen.add_argument("--json", action="store_true", help="print as JSON on stdout")
    keygen.set_defaults(func=cmd_keygen)
    approve = verbs.add_parser("approve", help="approve and sign a run's certificate",
                               description=APPROVE_HELP)
    approve.add_argument("run_dir", metavar="RUN_DIR", help="the run directory holding certificate.json")
    approve.add_argument("--by", required=True, metavar="NAME", help="the approver's name")
    approve.add_argument("--role", required=True, metavar="ROLE", help="the approver's role, e.g. 'Technical "
                                                                       "manager'")
    approve.add_argument("--key", required=True, metavar="KEYFILE", help="the approver's private key (PEM)")
    approve.add_argument("--station", metavar="STATION", help="the station file `labcal report --station` "
                                                              "took the Type B inputs from (default: the "
                                                              "station the run was journaled with)")
    approve.add_argument("--unchained", action="store_true",
                         help="approve a run journaled before digests (its journal is not tamper-evident; "
                              "the certificate then states no chain)")
    add_db_option(approve)
    approve.add_argument("--json", action="store_true", help="print as JSON on stdout")
    approve.set_defaults(func=cmd_approve)
    verify = verbs.add_parser("verify", help="verify a certificate's signature (exit 2 if it fails)")
    verify.add_argument("file", metavar="FILE", help="a certificate.json")
    verify.add_argument("--public-key", metavar="KEY",
                        help="verify against this public key (PEM) instead of the lab database's registered "
                             "approvers")
    verify.add_argument("--dcc", metavar="DCC", help="the DCC to check against the signed digest (default: "
                                                     "certificate.dcc.xml beside FILE)")
    add_db_option(verify)
    verify.add_argument("--json", action="store_true", help="print as JSON on stdout")
    verify.set_defaults(func=cmd_verify)
    approvers = verbs.add_parser("approvers", help="register, list and revoke the people who may approve",
                                 description="The lab database's register of approvers (name, role, Ed25519 "
                                             "public key), kept by a lab administrator.")
    which = approvers.add_subparsers(dest="approvers_verb", required=True, metavar="VERB")
    add = which.add_parser("add", help="register an approver's public key")
    add.add_argument("name", metavar="NAME", help="the approver's name, as `approve --by` gives it")
    add.add_argument("--role", required=True, metavar="ROLE",
                     help="the approver's role; 'lab server' for the key `labcal serve` signs with for "
                          "every approver signed in to it (it then signs as nobody itself)")
    add.add_argument("--public-key", required=True, metavar="FILE", help="their public key (PEM, .pub)")
    add_db_option(add)
    add.add_argument("--json", action="store_true", help="print as JSON on stdout")
    add.set_defaults(func=cmd_approvers_add)
    listing = which.add_parser("list", help="every registration, active and revoked")
    add_db_option(listing)
    listing.add_argument("--json", action="store_true", help="print as JSON on stdout")
    listing.set_defaults(func=cmd_approvers_list)
    revoke = which.add_parser("revoke", help="revoke an approver's key")
    revoke.add_argument("name", metavar="NAME")
    add_db_option(revoke)
    revoke.add_argument("--json", action="store_true", help="print as JSON on stdout")
    revoke.set_defaults(func=cmd_approvers_revoke)
