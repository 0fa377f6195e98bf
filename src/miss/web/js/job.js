// How a model job's progress is shown, shared by the volume page and the viewer.

import { el } from './format.js';

// The pipeline's stages in order, with words a physician reads.
export const STAGES = [
	[ 'queued', 'Waiting for a worker' ],
	[ 'preview', 'Preview' ],
	[ 'surface', 'Marching cubes' ],
	[ 'decimate', 'Decimation' ],
	[ 'check', 'Checking the error bound' ],
	[ 'lod', 'Levels of detail' ],
	[ 'write', 'Writing files' ],
	[ 'measure', 'Measuring the error' ],
	[ 'done', 'Done' ],
];

// Moments of a job that are not steps of the list above.
const OTHER_STAGES = { starting: 'Starting', read: 'Reading the scan', store: 'Saving the model' };

export function stageLabel( stage ) {
	const known = STAGES.find( ( [ key ] ) => key === stage );
	return known ? known[ 1 ] : OTHER_STAGES[ stage ] || stage || 'Starting';
}

// Fills a list with the stages, marking the ones passed and the current one.
// A stage the pipeline adds later (say 'read') is simply shown as text above.
export function renderStages( list, model ) {
	const stage = model.status === 'queued' ? 'queued' : model.status === 'done' ? 'done' : model.stage;
	const at = STAGES.findIndex( ( [ key ] ) => key === stage );
	list.replaceChildren( ...STAGES.map( ( [ key, label ], i ) => {
		const state = model.status === 'done' || ( at >= 0 && i < at ) ? 'done' : i === at ? 'active' : '';
		return el( `li${state ? '.' + state : ''}`, { dataset: { stage: key } }, label );
	} ) );
}

export function percent( model ) {
	return `${Math.round( ( model.progress || 0 ) * 100 )} %`;
}
