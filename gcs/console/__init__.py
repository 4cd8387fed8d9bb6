"""``magic console``: the operators' command console, a client of a running GCS (paper 6.2).

:mod:`.client` (zenoh: signed commands out, replies and GCS status in, loss of the GCS noticed),
:mod:`.completion` (commands, arguments, robot and OOI ids), :mod:`.macros` (function keys from a
YAML file), :mod:`.repl` (the prompt_toolkit REPL, ``-c`` and ``--script``). The command
language is :mod:`gcs.operator.grammar`, shared with the GCS.
"""
