"""`train.py`'s command-line errors in one line: jsonargparse reports a wrong value nested in a
subclass (`--data.spec.frame objct`) as a dozen lines of Union subtypes; the user needs the option,
the value and the choices.

    --data.spec.frame: 'objct' is not one of object, camera
"""

from __future__ import annotations

import re
import sys

from lightning.pytorch.cli import LightningArgumentParser

_KEY = re.compile(r'Parser key "([^"]+)":')
_LITERAL = re.compile(r"Expected a typing\.Literal\[(.*?)\]\. Got value: (.*)")
_CLASS = re.compile(r"Problem with given class_path '([^']+)'")
_OPTION = re.compile(r"Option '([^']+)' is not accepted")
_DETAIL = re.compile(r"(unrecognized arguments: .*|Expected .*|Got value: .*|Not a valid .*|No action for key .*"
                     r"|is not a valid .*|does not exist.*)")


def one_line(message: str) -> str:
    """The innermost cause of a jsonargparse error message, with the full option name."""
    lines = [line.strip() for line in message.strip().splitlines() if line.strip()]
    if len(lines) <= 1:
        return message.strip()
    keys = []  # nested keys down to the innermost problem: "data", "spec.frame" -> --data.spec.frame
    for line in lines:
        match = _KEY.match(line)
        if match:
            keys.append(match.group(1))
        literal = _LITERAL.search(line)
        if literal:
            choices = ", ".join(c.strip().strip("'\"") for c in literal.group(1).split(","))
            return f"--{'.'.join(keys)}: '{literal.group(2).strip()}' is not one of {choices}"
        option = _OPTION.search(line)
        if option:
            cls = next((m.group(1) for x in lines if (m := _CLASS.search(x))), None)
            owner = f" of {cls.rpartition('.')[2]} (`--{keys[0]}.help {cls}` lists them)" if cls and keys else ""
            return f"--{'.'.join([*keys, option.group(1)])}: not an option{owner}"
    if any("unrecognized arguments" in line for line in lines) and any(_CLASS.search(x) and "lightning." in x
                                                                       for x in lines):
        return (f"--{'.'.join(keys)}: options of the class come after the --config that names it "
                f"({next(line for line in lines if 'unrecognized' in line)})")
    details = [m.group(1) for line in lines if (m := _DETAIL.search(line)) and "NoneType" not in line
               and "NestedArg" not in line and "Given value type" not in line]
    where = f"--{'.'.join(keys)}: " if keys else ""
    return where + (details[-1] if details else lines[0])


class ForceArgumentParser(LightningArgumentParser):
    """Lightning's parser whose errors are one line (`train.py fit: error: ...`), then where the help is."""

    def error(self, message: str, ex: Exception | None = None):
        if not self.exit_on_error:
            return super().error(message, ex)
        prog = self.prog.replace(" [options]", "")
        sys.stderr.write(f"{prog}: error: {one_line(message)}\n")
        sys.stderr.write(f"(`{prog} --help` lists the options)\n")
        self.exit(2)
