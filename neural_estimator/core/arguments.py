"""Command lines whose usage errors are one line: the parser every front end uses (the CLI and the
process launcher), below both so that neither imports the other."""

from __future__ import annotations

import argparse
import sys

EXIT_BAD_INPUT = 2  # a usage problem: the exit status of every front end's bad command line


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line (no usage block) and suggest the closest verb or flag
    to a mistyped one ("did you mean"), with exit status 2. Sub-parsers inherit the class."""

    _argv: list[str] = []

    def parse_args(self, args=None, namespace=None):  # noqa: D102 - argparse's
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_args(args, namespace)

    def _flags(self) -> list[str]:
        """The option strings of this parser, or of the verb named on the command line."""
        parser = self
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                verb = next((a for a in self._argv if a in action.choices), None)
                if verb is not None:
                    parser = action.choices[verb]
        return [o for a in parser._actions for o in a.option_strings if o.startswith("--")]

    def error(self, message: str):  # noqa: D102 - argparse's
        import re

        from neural_estimator.core.options import did_you_mean

        m = re.match(r"unrecognized arguments: (.*)", message)
        if m:
            flags = [w.split("=", 1)[0] for w in m.group(1).split() if w.startswith("-")]
            if flags:
                message = f"unrecognized option {flags[0]}{did_you_mean(flags[0], self._flags())}"
                if len(flags) > 1:
                    message += f" (and {', '.join(flags[1:])})"
        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2))
            message = message.replace(f"'{m.group(1)}'", f"'{m.group(1)}'{did_you_mean(m.group(1), choices)}", 1)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
