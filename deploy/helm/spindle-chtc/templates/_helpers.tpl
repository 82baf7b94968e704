{{/*
Names, labels, the values checks and the per-cell settings file (chtc.toml).
*/}}

{{- define "chtc.labels" -}}
app.kubernetes.io/name: spindle-chtc
app.kubernetes.io/instance: {{ .Release.Name }}
app.kubernetes.io/version: {{ .Chart.AppVersion | quote }}
app.kubernetes.io/managed-by: {{ .Release.Service }}
helm.sh/chart: {{ printf "%s-%s" .Chart.Name .Chart.Version | replace "+" "_" }}
{{- end -}}

{{/* The selector of one cell's pod: (dict "root" $ "cell" $cell) */}}
{{- define "chtc.cellSelector" -}}
app.kubernetes.io/name: spindle-chtc
app.kubernetes.io/instance: {{ .root.Release.Name }}
spindle-chtc/cell: {{ .cell.name }}
{{- end -}}

{{/* One cell's resource name: <release>-<cell>, refused over 63 characters (no silent truncation). */}}
{{- define "chtc.cellName" -}}
{{- $name := printf "%s-%s" .root.Release.Name .cell.name -}}
{{- if gt (len $name) 63 -}}
{{- fail (printf "cells: %q (release + cell name) is longer than 63 characters; shorten the release or cell name" $name) -}}
{{- end -}}
{{- $name -}}
{{- end -}}

{{- define "chtc.image" -}}
{{- printf "%s:%s" (required "image.repository is required" .Values.image.repository) (default .Chart.AppVersion .Values.image.tag) -}}
{{- end -}}

{{/*
Every check on the values, with a message naming the bad entry. Included by every template, so a bad values
file renders nothing. Spindle ids are unique across the whole plant (they key the rows of the shared database);
names of cells are unique DNS labels; DAQ addresses and CAN channels are unique within a cell (the instance
refuses them too, but only at start); a named geometry must be in .Values.geometries.
*/}}
{{- define "chtc.validate" -}}
{{- $cells := .Values.cells -}}
{{- if not (kindIs "slice" $cells) -}}
{{- fail "cells: must be a list of cells (see values.yaml)" -}}
{{- end -}}
{{- if not $cells -}}
{{- fail "cells: empty; give at least one cell with its spindles (see values.yaml)" -}}
{{- end -}}
{{- if not .Values.database.existingSecret -}}
{{- fail "database.existingSecret: required, the name of the Secret holding the shared database URL (see values.yaml)" -}}
{{- end -}}
{{- if hasKey .Values.config "spindles" -}}
{{- fail "config.spindles: not here; spindles are listed under cells[].spindles" -}}
{{- end -}}
{{- range $key := list "spindle" "api" -}}
{{- if hasKey $.Values.config $key -}}
{{- fail (printf "config.%s: set by the chart (spindle ids from cells[].spindles, [api] host/port from api.port); remove it" $key) -}}
{{- end -}}
{{- end -}}
{{- range $section, $body := .Values.config -}}
{{- if not (kindIs "map" $body) -}}
{{- fail (printf "config.%s: must be a table of keys (a TOML section), got %v" $section $body) -}}
{{- end -}}
{{- end -}}
{{- range $name, $_ := .Values.geometries -}}
{{- if not (regexMatch "^[-._a-zA-Z0-9]+$" $name) -}}
{{- fail (printf "geometries: key %q is not a file name (letters, digits, '-', '_', '.')" $name) -}}
{{- end -}}
{{- end -}}
{{- $cfgModbus := default dict .Values.config.modbus -}}
{{- $cfgCan := default dict .Values.config.can -}}
{{- $ids := dict -}}
{{- $cellNames := dict -}}
{{- range $i, $cell := $cells -}}
{{- $where := printf "cells[%d]" $i -}}
{{- $name := required (printf "%s.name: required (a DNS label, e.g. cell1)" $where) $cell.name -}}
{{- if not (regexMatch "^[a-z0-9]([-a-z0-9]*[a-z0-9])?$" (toString $name)) -}}
{{- fail (printf "%s.name: %q is not a DNS label (lower-case letters, digits and '-')" $where (toString $name)) -}}
{{- end -}}
{{- if hasKey $cellNames $name -}}
{{- fail (printf "%s.name: %q is also %s.name; cell names must be unique" $where $name (get $cellNames $name)) -}}
{{- end -}}
{{- $_ := set $cellNames $name $where -}}
{{- if not $cell.spindles -}}
{{- fail (printf "%s.spindles: empty; a cell hosts at least one spindle" $where) -}}
{{- end -}}
{{- $daqs := dict -}}
{{- $buses := dict -}}
{{- range $j, $s := $cell.spindles -}}
{{- $at := printf "%s.spindles[%d]" $where $j -}}
{{- $id := required (printf "%s.id: required (a stable spindle name, unique in the plant)" $at) $s.id -}}
{{- if not (regexMatch "^[A-Za-z][A-Za-z0-9_-]{0,62}$" (toString $id)) -}}
{{- fail (printf "%s.id: %q is not a spindle id (a letter, then up to 62 letters, digits, '_' or '-')" $at (toString $id)) -}}
{{- end -}}
{{- if hasKey $ids $id -}}
{{- fail (printf "%s.id: %q is also %s.id; spindle ids must be unique in the plant (they key the shared database)" $at $id (get $ids $id)) -}}
{{- end -}}
{{- $_ := set $ids $id $at -}}
{{- $modbus := default dict $s.modbus -}}
{{- $host := required (printf "%s.modbus.host: required, the address of this spindle's temperature DAQ" $at) $modbus.host -}}
{{- $daq := printf "%v:%v/unit %v" $host (default (default 5020 $cfgModbus.port) $modbus.port) (default (default "default" $cfgModbus.unit) $modbus.unit) -}}
{{- if hasKey $daqs $daq -}}
{{- fail (printf "%s.modbus: DAQ %s is also %s's; each spindle of a cell needs its own DAQ address" $at $daq (get $daqs $daq)) -}}
{{- end -}}
{{- $_ := set $daqs $daq $at -}}
{{- $can := default dict $s.can -}}
{{- $bus := printf "%v:%v" (default (default "virtual" $cfgCan.interface) $can.interface) (default (default "chtc" $cfgCan.channel) $can.channel) -}}
{{- if hasKey $buses $bus -}}
{{- fail (printf "%s.can: bus %s is also %s's; each spindle of a cell needs its own CAN channel" $at $bus (get $buses $bus)) -}}
{{- end -}}
{{- $_ := set $buses $bus $at -}}
{{- if $s.geometry -}}
{{- if not (hasKey $.Values.geometries $s.geometry) -}}
{{- fail (printf "%s.geometry: %q is not a key of geometries (give it with --set-file 'geometries.%s=PATH')" $at $s.geometry (replace "." "\\." $s.geometry)) -}}
{{- end -}}
{{- end -}}
{{- end -}}
{{- end -}}
{{- end -}}

{{/* A TOML value from a values node: tables inline, keys quoted, scalars as JSON (a valid TOML literal). */}}
{{- define "chtc.tomlValue" -}}
{{- if kindIs "map" . -}}
{{- $parts := list -}}
{{- range $k, $v := . -}}
{{- $parts = append $parts (printf "%s = %s" (toJson $k) (include "chtc.tomlValue" $v)) -}}
{{- end -}}
{ {{- join ", " $parts -}} }
{{- else if kindIs "slice" . -}}
{{- $parts := list -}}
{{- range . -}}
{{- $parts = append $parts (include "chtc.tomlValue" .) -}}
{{- end -}}
[{{ join ", " $parts }}]
{{- else if kindIs "invalid" . -}}
{{- fail "config: a null value has no TOML form; delete the key to keep its default" -}}
{{- else -}}
{{- toJson . -}}
{{- end -}}
{{- end -}}

{{/* The geometry file names one cell uses, sorted: (dict "root" $ "cell" $cell) */}}
{{- define "chtc.cellGeometries" -}}
{{- $names := dict -}}
{{- range .cell.spindles -}}
{{- if .geometry -}}
{{- $_ := set $names .geometry true -}}
{{- end -}}
{{- end -}}
{{- keys $names | sortAlpha | toJson -}}
{{- end -}}

{{/* One cell's settings file (chtc.toml): (dict "root" $ "cell" $cell) */}}
{{- define "chtc.cellConfig" -}}
{{- $root := .root -}}
{{- $fixed := dict "api" (dict "host" "0.0.0.0" "port" $root.Values.api.port) -}}
{{- $config := mergeOverwrite (deepCopy (default dict $root.Values.config)) $fixed -}}
# chtc.toml of cell {{ .cell.name }}, written by the spindle-chtc chart {{ $root.Chart.Version }} (release {{ $root.Release.Name }}).
# The database URL and the API token come from the environment (Secrets), never from this file.
{{- range $section, $body := $config }}

[{{ $section }}]
{{- range $key, $value := $body }}
{{ toJson $key }} = {{ include "chtc.tomlValue" $value }}
{{- end }}
{{- end }}
{{- range .cell.spindles }}

[[spindles]]
"id" = {{ toJson .id }}
{{- with .description }}
"description" = {{ toJson . }}
{{- end }}
"modbus" = {{ include "chtc.tomlValue" (default dict .modbus) }}
{{- with .can }}
"can" = {{ include "chtc.tomlValue" . }}
{{- end }}
{{- with .geometry }}
"geometry" = {{ printf "geometry/%s" . | toJson }}
{{- end }}
{{- end }}
{{ end -}}

{{/* One cell's ConfigMap data (its checksum is the pod's checksum/config): (dict "root" $ "cell" $cell) */}}
{{- define "chtc.cellConfigMapData" -}}
chtc.toml: |
  {{- include "chtc.cellConfig" . | nindent 2 }}
{{- range $name := include "chtc.cellGeometries" . | fromJsonArray }}
{{ printf "geometry.%s" $name }}: {{ get $.root.Values.geometries $name | toJson }}
{{- end }}
{{- end -}}
