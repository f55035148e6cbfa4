from __future__ import annotations

from ..evaluate import format_summary, merge


def merge_cmd(args) -> int:
    res = merge(args.parts, out=args.out, force=args.force, progress=not args.quiet)
    print(format_summary(res))
    print(f"wrote {args.out}")
    return 0
