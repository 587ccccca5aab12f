"""Shell completion for `deadreckon`, written from the argument parser itself (so a new command or option
completes without an edit here): `source <(deadreckon completion bash)`."""

from __future__ import annotations

import argparse
import shlex

# options whose value is a serial port, completed from the terminal devices there are
PORT_OPTIONS = ("--port",)


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse keeps its sub-commands here; there is no public accessor
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> tuple[list[str], dict[str, list[str]]]:
    """Every option string, and the choices of those that take one from a list."""
    flags, choices = [], {}
    for action in parser._actions:
        flags += action.option_strings
        if action.option_strings and action.choices:
            for flag in action.option_strings:
                choices[flag] = [str(c) for c in action.choices]
    return flags, choices


def bash_script(parser: argparse.ArgumentParser) -> str:
    """A bash completion function for the commands, their options and the options' choices; files otherwise."""
    commands = _commands(parser)
    top_flags, _ = _options(parser)
    cases = []
    for name, sub in commands.items():
        flags, choices = _options(sub)
        value_cases = "".join(f"            {shlex.quote(flag)}) COMPREPLY=($(compgen -W "
                              f"{shlex.quote(' '.join(values))} -- \"$cur\")); return;;\n"
                              for flag, values in choices.items())
        ports = "|".join(flag for flag in PORT_OPTIONS if flag in flags)
        if ports:
            value_cases += (f"            {ports}) COMPREPLY=($(compgen -W "
                            '"$(ls /dev/ttyUSB* /dev/ttyACM* 2>/dev/null)" -- "$cur")); return;;\n')
        positional = [a for a in sub._actions if not a.option_strings and a.choices]
        words = " ".join(str(c) for a in positional for c in a.choices)
        cases.append(
            f"        {name})\n"
            f'          case "$prev" in\n{value_cases}          esac\n'
            f"          opts={shlex.quote(' '.join(flags))}; words={shlex.quote(words)};;\n")
    return (
        "# bash completion for deadreckon: source <(deadreckon completion bash)\n"
        "_deadreckon() {\n"
        '    local cur="${COMP_WORDS[COMP_CWORD]}" prev="${COMP_WORDS[COMP_CWORD-1]}" opts="" words=""\n'
        "    if [ \"$COMP_CWORD\" -eq 1 ]; then\n"
        f"        COMPREPLY=($(compgen -W {shlex.quote(' '.join(list(commands) + top_flags))} -- \"$cur\")); return\n"
        "    fi\n"
        '    case "${COMP_WORDS[1]}" in\n'
        + "".join(cases) +
        "    esac\n"
        '    if [[ "$cur" == -* ]]; then\n'
        '        COMPREPLY=($(compgen -W "$opts" -- "$cur"))\n'
        '    elif [ -n "$words" ]; then\n'
        '        COMPREPLY=($(compgen -W "$words" -- "$cur"))\n'
        "    else\n"
        '        COMPREPLY=($(compgen -f -- "$cur"))\n'
        "    fi\n"
        "}\n"
        "complete -o filenames -o bashdefault -F _deadreckon deadreckon\n"
    )
