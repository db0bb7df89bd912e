"""kinfly ground station: receives a drone's depth keyframes over LCM, fuses them at full
resolution and sends back signed pose corrections. The message types are the generated `kinfly`
package (from proto/)."""

__version__ = "0.1.0"
