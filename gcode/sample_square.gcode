; ambots sample: a 20 x 20 mm square wall, 3 layers of 0.2 mm, centred on the origin.
; Hand-written, PrusaSlicer-style (relative E, ;LAYER_CHANGE comments); 0.45 mm bead,
; 1.75 mm filament.  Try: python -m ambots info gcode/sample_square.gcode
G21 ; millimetres
G90 ; absolute XYZ
M83 ; relative E
M104 S210 ; nozzle temperature
M109 S210 ; wait for it
;LAYER_CHANGE
;Z:0.2
G92 E0
G1 Z0.2 F600
G1 X-10 Y-10 F6000
G1 E0.8 F2100 ; deretract
G1 F1200
G1 X10 Y-10 E0.67698
G1 X10 Y10 E0.67698
G1 X-10 Y10 E0.67698
G1 X-10 Y-10 E0.67698
G1 E-0.8 F2100 ; retract
;LAYER_CHANGE
;Z:0.4
G92 E0
G1 Z0.4 F600
G1 X-10 Y-10 F6000
G1 E0.8 F2100 ; deretract
G1 F1200
G1 X10 Y-10 E0.67698
G1 X10 Y10 E0.67698
G1 X-10 Y10 E0.67698
G1 X-10 Y-10 E0.67698
G1 E-0.8 F2100 ; retract
;LAYER_CHANGE
;Z:0.6
G92 E0
G1 Z0.6 F600
G1 X-10 Y-10 F6000
G1 E0.8 F2100 ; deretract
G1 F1200
G1 X10 Y-10 E0.67698
G1 X10 Y10 E0.67698
G1 X-10 Y10 E0.67698
G1 X-10 Y-10 E0.67698
G1 E-0.8 F2100 ; retract
M104 S0 ; heater off
M84 ; motors off
