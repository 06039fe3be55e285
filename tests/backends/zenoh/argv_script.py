"""A script that parses its arguments when imported (argparse at module level, as many do).

On zenoh every worker imports it too, to rebuild its flows; it must parse the arguments the
script was started with, which argparse would refuse otherwise (test_lifecycle.py, section 6)::

    python tests/backends/zenoh/argv_script.py --rate 7 --namespace NS
"""

import argparse

from retriever import Flow, Pipeline, Rate

parser = argparse.ArgumentParser()
parser.add_argument("--rate", type=int, required=True)
parser.add_argument("--namespace", required=True)
args = parser.parse_args()  # no defaults: unknown or missing arguments exit 2


class FromArgv(Flow[None, int]):
    def step(self, inp: None) -> int:
        return args.rate  # parsed in the process that steps it, the worker; not a constructor argument


with Pipeline("argv") as pipe:
    FromArgv() @ Rate(hz=10)

if __name__ == "__main__":
    pipe.run(duration=0.5, backend="zenoh", namespace=args.namespace, quiet=True)
    print(sorted({event.value for event in pipe.trace.events}))
