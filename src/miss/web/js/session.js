// The signed-in user in the top bar, with a log-out button.

import { api } from './api.js';
import { el } from './format.js';

export async function showSession( topbar = document.querySelector( '.topbar' ) ) {
	const logout = async () => {
		try {
			await api.logout();
		} finally {
			location.assign( '/login' );
		}
	};
	try {
		const me = await api.me();
		topbar.append( el( 'span.session',
			el( 'span', { id: 'session-user', title: me.admin ? 'administrator' : 'user' }, me.name ),
			me.admin && me.name.toLowerCase() !== 'admin' ? el( 'span.badge', {}, 'administrator' ) : null,
			el( 'button.small', { type: 'button', id: 'logout', onclick: logout }, 'Log out' ) ) );
		return me;
	} catch ( err ) {
		return null; // api.js has already sent a 401 to the login page
	}
}
