"""kinfly ground station: receives a drone's depth keyframes over LCM, fuses them at full
resolution and sends back signed pose corrections. The message types are the generated `kinfly`
package (from proto/)."""
import os

__version__ = "0.1.0"

# The engine's parallel loops are GNU OpenMP's, whose threads spin at the end of each loop while
# they wait for the others. On a laptop busy with other work a spinning thread holds the core
# the thread it waits for needs: beside two busy processes on 2 cores a keyframe took 280-410 ms
# to refine instead of 73-94 ms with passive waiting (docs/ground.md, "Threads"). libgomp reads
# this when it is loaded, with the native module, which every module here imports after this.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")
