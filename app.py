"""UniRelight Studio: `python app.py` serves the relighting app on localhost and opens a browser.

    python app.py                       # local desktop launch on the shipped default model
    python app.py --share               # also a public link for reviewers (needs internet)
    python app.py --auth USER:PASS      # ask for a login
    python app.py --model DIR           # a local model folder, e.g. the released weights
    python app.py --precision fp32      # compute precision (default auto: bf16 only where it is faster)
"""

from __future__ import annotations

import sys
from pathlib import Path

from relight_core.arguments import OneLineParser, finite_float, int_range
from relight_core.errors import InputError
from ui.server import ServerOptions, start


def parse_args(argv: list[str] | None = None) -> ServerOptions:
    """The command line as ServerOptions."""
    parser = OneLineParser(prog="app.py", description="UniRelight Studio: relight images and videos in a browser.")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0 for the LAN)")
    parser.add_argument("--port", type=int_range(1, 65535, "port"), default=None, help="port (default: first free from 7860)")
    parser.add_argument("--model", default="default",
                        help="'default' (shipped model), a preset name such as 'tiny', or a model folder")
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16", "fp16"), default=None,
                        help="compute precision (default: the model's, normally auto: bf16 where this machine "
                             "runs it faster than fp32, else fp32); fp16 only on a CUDA GPU")
    parser.add_argument("--share", action="store_true", help="create a public share link for reviewers")
    parser.add_argument("--share-timeout", type=finite_float(0.0, 600.0, low_open=True, what="timeout"), default=5.0,
                        help="seconds to try reaching the share server before serving locally only")
    parser.add_argument("--model-choice", choices=("on", "off"), default=None,
                        help="let visitors load another model folder (default: on only for a local-only server)")
    parser.add_argument("--auth", default=None, metavar="USER:PASS", help="protect the app with a login")
    parser.add_argument("--no-browser", action="store_true", help="do not open a browser tab")
    parser.add_argument("--max-upload-mb", type=int_range(1, 1_000_000, "upload limit"), default=500, help="largest accepted upload, in MB")
    parser.add_argument("--queue-size", type=int_range(1, 10_000, "queue size"), default=16, help="jobs that may wait in line")
    parser.add_argument("--concurrency", type=int_range(1, 64, "concurrency"), default=1, help="model runs at the same time")
    parser.add_argument("--temp-dir", type=Path, default=None,
                        help="folder for uploads and results (default: a temporary one removed at exit)")
    args = parser.parse_args(argv)
    auth = None
    if args.auth is not None:
        user, sep, password = args.auth.partition(":")
        if not sep or not user or not password:
            parser.error("--auth takes USER:PASS, for example --auth alice:s3cret")
        auth = (user, password)
    return ServerOptions(host=args.host, port=args.port, model=args.model, precision=args.precision,
                         share=args.share,
                         share_timeout_s=args.share_timeout, auth=auth, inbrowser=not args.no_browser,
                         max_upload_mb=args.max_upload_mb, queue_size=args.queue_size,
                         concurrency=args.concurrency, temp_dir=args.temp_dir,
                         model_choice=None if args.model_choice is None else args.model_choice == "on")


def main(argv: list[str] | None = None) -> int:
    """Serve until interrupted; a bad model or precision ends with one sentence and exit code 2."""
    options = parse_args(argv)
    try:
        start(options, block=True)  # SIGTERM is handled like Ctrl+C from here on
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # before the server was up (while loading the model)
        print("stopped.", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
